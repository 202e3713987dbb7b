"""Relational queries (issue 27): right-target rate per relation type, relational vs explicit visible
mIoU and colour terms on synthetic scenes, queries generated from the ground truth where the answer is
unambiguous by a stated margin, plus hand-written free-form phrasings.

    python benchmarks/bench_relations.py [--seeds 411 ... 420] [--objects 10] [--same-category 3] [--views 30]
                                         [--supervision oracle default] [--json] [--record]

Each scene (`rg synth`, 320x240, 3 of its objects sharing a category with another: several cups of
different colours, two screwdrivers, two bowls) is mapped, supervised (oracle: ground-truth masks and names, the 3D
part alone; default: the offline models) and asked from its first test camera. Templates (Sr3D-style):
- near: "the object closest to the A" when A's nearest and second-nearest neighbours (object
  centres) differ by >= MARGIN; between: "the object between the A and the B" (3 per scene);
- left / right / front / behind: "the object left of the A" seen from the camera, the nearest to A
  on that side by >= MARGIN (2 per scene and side);
- superlative: biggest / smallest (box volume, 30 % apart), tallest (box height, 30 % apart), nearest
  to the camera (by >= MARGIN), over all objects or a category with >= 2 members;
- colour: "the <colour> <category>" when the category's members have different colour terms (a
  name that says the colour, "the blue cup", is asked too: it takes the explicit path);
- ordinal: "the second <category> from the left" (image x apart by >= 0.05 of the focal length);
- count: "how many <category> are there" (every category with a member, a plural a person would use);
- all: "all the <category>" (the set must match).
Categories: cup, fruit, screwdriver, bowl, tool (WordNet hypernyms, relations._is_a). Colour terms of
the ground truth come from the object's visible pixels in the test views (perception.colour_names).
FREEFORM holds hand-written phrasings (written before any run), filled from the same ground truth.
Right = the answer's target is the expected object (count: the number; all: the set). Relational
mIoU: the visible IoU of single-object answers against the expected object over the test views
where it shows (>= 20 px), wrong answers included; explicit mIoU: the object's name asked on the same
views. Writes relations.png.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from rg_core.config import RGConfig, SynthConfig  # noqa: E402
from rg_core.synth.generator import default_objects_dir, generate_scene  # noqa: E402
from _common import add_output_flags, finish, pyplot, save_figure  # noqa: E402

MARGIN = 0.03          # metres between the expected answer and the runner-up
CATEGORIES = {"cup": "cups", "fruit": "fruits", "screwdriver": "screwdrivers", "bowl": "bowls", "tool": "tools"}
ORDINAL = {1: "first", 2: "second", 3: "third"}
# Hand-written phrasings ({a}, {b}: anchor names; {c}: category, {cs}: its plural; {k}: colour term),
# written before any run; kind -> phrasings. One of each kind per scene, in turn.
FREEFORM = {
    "near": ["what's right next to the {a}?", "which object is closest to the {a}", "the thing beside the {a}",
             "find whatever is near the {a}", "show me the item next to the {a}",
             "pick up the object that is closest to the {a}", "grab the thing next to the {a}",
             "where is the object nearest to the {a}?", "the one beside the {a}", "hand me the item closest to the {a}"],
    "between": ["what is between the {a} and the {b}?", "the object in between the {a} and the {b}",
                "find the thing between the {a} and the {b}", "show me what sits between the {a} and the {b}",
                "the item between the {a} and the {b}, please", "pick up whatever is between the {a} and the {b}"],
    "left": ["the object to the left of the {a}", "what's on the left of the {a}?", "find the thing left of the {a}",
             "show me the item to the left of the {a}", "grab the object on the left of the {a}"],
    "right": ["the object to the right of the {a}", "what's on the right of the {a}?", "find the thing right of the {a}",
              "show me the item to the right of the {a}", "grab the object on the right of the {a}"],
    "front": ["the object in front of the {a}", "what is in front of the {a}?"],
    "behind": ["the object behind the {a}", "what is behind the {a}?"],
    "superlative": ["which is the biggest object?", "show me the largest thing", "the smallest item on the table",
                    "find the tiniest object", "what's the biggest {c}?", "the smallest {c}, please",
                    "pick up the largest {c}", "grab the smallest thing"],
    "count": ["how many {cs} are there?", "how many {cs} do you see", "count the {cs}", "how many {cs} can you see?",
              "how many {cs} are on the table?", "how many {cs} are in the scene", "count all the {cs}",
              "how many {cs} are there on the table"],
    "colour": ["the {k} {c}", "pick up the {k} {c}", "show me the {k} {c}", "where is the {k} {c}?",
               "grab the {k} {c}", "find the {k} {c}", "hand me the {k} {c}", "the {k} {c}, please"],
    "ordinal": [("the second {c} from the left", 2), ("the first {c} from the right", -1), ("the leftmost {c}", 1),
                ("the rightmost {c}", -1), ("the {c} on the left", 1), ("the {c} on the far right", -1)],
    "all": ["all the {cs}", "show me all the {cs}", "every {c}", "find all {cs}"],
}


def _plural(name: str) -> str:
    if name.endswith("s"):   # scissors, glasses: already plural
        return name
    if name.endswith("fe"):
        return name[:-2] + "ves"
    return name + ("es" if name.endswith(("s", "sh", "ch", "x")) else "s")


def gt_colours(scene, min_px: int = 20) -> dict[str, str]:
    """The basic colour term of each object's visible pixels over the test views."""
    from rg_core.perception.colour_names import colour_term

    px: dict[int, list] = {}
    for f in scene.test:
        ids, rgb = f.load_visible_mask(), f.load_rgb()
        for o in scene.objects:
            m = ids == o.id
            if m.sum() >= min_px:
                px.setdefault(o.id, []).append(rgb[m])
    return {o.name: colour_term(np.concatenate(px[o.id])) for o in scene.objects if o.id in px}


def what_it_got(g, q: dict, r) -> object:
    """What an answer `r` to query `q` says, in the form of q["expect"]: the count, the set of names
    (all), else the target name ("" when unsuccessful)."""
    if q["kind"] == "count":
        return len(r.objects) if r.success else 0
    if q["kind"] == "all":
        graph = g.scene_graph()
        return sorted(next((o.name for o in graph if o.obj is x), "?") for x in r.objects) if r.success else []
    return r.target if r.success else ""


def queries(scene, rng, colours: dict[str, str], cam: np.ndarray, K: np.ndarray) -> list[dict]:
    """{kind, text, expect, template} from the scene's ground truth: expect is a name (single answer),
    an int (count) or a sorted list of names (all); template "generated" or "freeform"."""
    from rg_core.grounding.relations import _is_a

    objs = scene.objects
    c = {o.name: (np.asarray(o.aabb_min) + np.asarray(o.aabb_max)) / 2 for o in objs}
    ext = {o.name: np.asarray(o.aabb_max) - np.asarray(o.aabb_min) for o in objs}
    vol = {n: float(np.prod(e)) for n, e in ext.items()}
    names = sorted(c)
    w2c = np.linalg.inv(cam)
    pc = {n: w2c[:3, :3] @ c[n] + w2c[:3, 3] for n in names}
    ux = {n: float(pc[n][0] / pc[n][2]) for n in names}          # image x / focal length
    cats = {k: sorted(n for n in names if _is_a(n, k)) for k in CATEGORIES}
    gen: dict[str, list[dict]] = {}

    def add(kind, text, expect, **slots):
        gen.setdefault(kind, []).append({"kind": kind, "text": text, "expect": expect, "slots": slots})

    def nearest(point, pool, exclude):
        d = sorted((float(np.linalg.norm(c[n] - point)), n) for n in pool if n not in exclude)
        return d[0][1] if d and (len(d) == 1 or d[1][0] - d[0][0] >= MARGIN) else None

    for a in names:
        e = nearest(c[a], names, {a})
        if e:
            add("near", f"the object closest to the {a}", e, a=a)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    rng.shuffle(pairs)
    for a, b in pairs:
        e = nearest((c[a] + c[b]) / 2, names, {a, b})
        if e and len(gen.get("between", [])) < 3:
            add("between", f"the object between the {a} and the {b}", e, a=a, b=b)
    sides = {"left": lambda n, a: pc[n][0] < pc[a][0], "right": lambda n, a: pc[n][0] > pc[a][0],
             "front": lambda n, a: pc[n][2] < pc[a][2], "behind": lambda n, a: pc[n][2] > pc[a][2]}
    words = {"left": "left of", "right": "right of", "front": "in front of", "behind": "behind"}
    for side, test in sides.items():
        for a in rng.permutation(names):
            e = nearest(c[a], [n for n in names if n != a and test(n, a)], {a})
            if e and len(gen.get(side, [])) < 2:
                add(side, f"the object {words[side]} the {a}", e, a=str(a))
    for label, pool in [("object", names)] + [(k, v) for k, v in cats.items() if len(v) >= 2]:
        by_vol = sorted(pool, key=lambda n: vol[n])
        if vol[by_vol[-1]] >= 1.3 * vol[by_vol[-2]]:
            add("superlative", f"the biggest {label}", by_vol[-1], c=label, which="biggest")
        if vol[by_vol[1]] >= 1.3 * vol[by_vol[0]]:
            add("superlative", f"the smallest {label}", by_vol[0], c=label, which="smallest")
        by_h = sorted(pool, key=lambda n: ext[n][2])
        if ext[by_h[-1]][2] >= 1.3 * ext[by_h[-2]][2]:
            add("superlative", f"the tallest {label}", by_h[-1], c=label, which="tallest")
        d = sorted((float(np.linalg.norm(pc[n])), n) for n in pool)
        if d[1][0] - d[0][0] >= MARGIN:
            add("superlative", f"the {label} nearest to the camera", d[0][1], c=label, which="nearest")
    for k, pool in cats.items():
        if pool:
            add("count", f"how many {CATEGORIES[k]} are there", len(pool), c=k, cs=CATEGORIES[k])
        if len(pool) >= 2:
            add("all", f"all the {CATEGORIES[k]}", pool, c=k, cs=CATEGORIES[k])
            terms = [colours.get(n, "").split()[-1] if colours.get(n) else "" for n in pool]
            for n, t in zip(pool, terms):   # unambiguous: one member of that colour, no other named so
                if t and terms.count(t) == 1 and not any(t in m.split() for m in pool if m != n):
                    add("colour", f"the {t} {k}", n, c=k, k=t)
            order = sorted(pool, key=lambda n: ux[n])
            gaps = np.diff([ux[n] for n in order])
            if gaps.min() >= 0.05:
                for i in range(min(len(order), 3)):
                    add("ordinal", f"the {ORDINAL[i + 1]} {k} from the left", order[i], c=k, order=order)
                add("ordinal", f"the first {k} from the right", order[-1], c=k, order=order)
    a = names[int(rng.integers(len(names)))]
    add("count", f"how many {_plural(a)} are there", sum(n == a or _is_a(n, a) for n in names), c=a, cs=_plural(a))
    out = [{**q, "template": "generated"} for qs in gen.values() for q in qs]
    return out + freeform(gen, rng)


def freeform(gen: dict[str, list[dict]], rng) -> list[dict]:
    """One hand-written phrasing per kind whose generated query fits it, the expected answer carried over."""
    out = []
    for kind, phrasings in FREEFORM.items():
        base = gen.get(kind, [])
        if kind == "ordinal":   # (phrasing, rank from the left; -1: the last), per category
            for q in {q["slots"]["c"]: q for q in base}.values():
                p, n = phrasings[int(rng.integers(len(phrasings)))]
                order = q["slots"]["order"]
                if n <= len(order):
                    out.append({"kind": kind, "text": p.format(c=q["slots"]["c"]), "expect": order[n - 1 if n > 0 else -1],
                                "template": "freeform"})
            continue
        if kind == "superlative":   # the phrasing's word and whether it names a category must fit the query
            words = {"biggest": ("biggest", "largest"), "smallest": ("smallest", "tiniest")}
            cands = [(q, p) for q in base for p in phrasings if any(w in p for w in words.get(q["slots"]["which"], ()))
                     and ("{c}" in p) == (q["slots"]["c"] != "object")]
        else:
            cands = [(q, p) for q in base for p in phrasings]
        if cands:
            q, p = cands[int(rng.integers(len(cands)))]
            s = {"a": "", "b": "", "c": "", "cs": "", "k": "", **q["slots"]}
            out.append({"kind": kind, "text": p.format(**s), "expect": q["expect"], "template": "freeform"})
    return out


def run_scene(path: Path, seed: int, supervision: str) -> tuple[list[dict], dict]:
    from rg_core.eval.grounding import iou
    from rg_core.grounding.build import build_grounder
    from rg_core.io.captures import read_scene

    scene = read_scene(path)
    g, _ = build_grounder(scene, RGConfig(), supervision)
    f0 = scene.test[0]
    cam = f0.cam_to_world
    by_name = {o.name: o for o in scene.objects}
    views = [(f, f.load_visible_mask()) for f in scene.test]

    def miou(res, name) -> float | None:
        oid = by_name[name].id
        vals = []
        for f, ids in views:
            gt = ids == oid
            if gt.sum() < 20:
                continue
            _, visible = g.masks(res, f.intrinsics.K, f.cam_to_world, f.intrinsics.width, f.intrinsics.height)
            vals.append(iou(visible, gt))
        return float(np.mean(vals)) if vals else None

    colours = gt_colours(scene)
    rows = []
    for i, q in enumerate(queries(scene, np.random.default_rng(seed), colours, cam, f0.intrinsics.K)):
        t = time.perf_counter()
        r = g.ground(q["text"], cam_to_world=cam)
        dt = time.perf_counter() - t
        got = what_it_got(g, q, r)
        row = {**{k: v for k, v in q.items() if k != "slots"}, "scene": seed, "got": got, "right": got == q["expect"],
               "seconds": dt, "first": i == 0, "explanation": r.explanation or r.message, "graph": "graph" in r.timings}
        if isinstance(q["expect"], str) and r.objects:
            row["miou_visible"] = miou(r, q["expect"])
        elif isinstance(q["expect"], str):
            row["miou_visible"] = 0.0
        rows.append(row)
    graph = g.scene_graph()
    named = {o.name: o for o in graph}
    col = {n: (named[n].colour.split()[-1], colours[n].split()[-1]) for n in colours if n in named}
    explicit = [m for m in (miou(g.ground(o.name, mode="explicit"), o.name) for o in scene.objects) if m is not None]
    return rows, {"colour": col, "explicit_miou": explicit, "graph_objects": len(graph), "objects": len(scene.objects)}


def summarise(rows: list[dict], scenes: list[dict]) -> dict:
    groups = {k: [r for r in rows if r["kind"] == k] for k in sorted({r["kind"] for r in rows})}
    groups["every kind"] = rows
    kinds = {}
    for k, rs in groups.items():
        gen = [r for r in rs if r["template"] == "generated"]
        free = [r for r in rs if r["template"] == "freeform"]
        m = [r["miou_visible"] for r in gen if r.get("miou_visible") is not None]
        pct = lambda xs: round(100 * float(np.mean([r["right"] for r in xs])), 1) if xs else None  # noqa: E731
        kinds[k] = {"queries": len(gen), "right_pct": pct(gen), "freeform": len(free), "freeform_right_pct": pct(free),
                    "miou_visible": round(100 * float(np.mean(m)), 1) if m else None}
    col = [v for s in scenes for v in s["colour"].values()]
    exp = [v for s in scenes for v in s["explicit_miou"]]
    return {"kinds": kinds, "colour_right_pct": round(100 * float(np.mean([a == b for a, b in col])), 1),
            "colour_wrong": [f"{n}: {a} (truth {b})" for s in scenes for n, (a, b) in s["colour"].items() if a != b],
            "colour_objects": len(col), "explicit_miou_visible": round(100 * float(np.mean(exp)), 1),
            "graph_objects": sum(s["graph_objects"] for s in scenes), "objects": sum(s["objects"] for s in scenes),
            "warm_query_s": float(np.median([r["seconds"] for r in rows if not r["first"] and r["graph"]])),
            "first_query_s": float(np.median([r["seconds"] for r in rows if r["first"]]))}


def to_rows(report: dict) -> tuple[list[dict], str]:
    out = []
    dash = lambda v: "-" if v is None else v   # noqa: E731
    for sup, s in report["supervisions"].items():
        for kind, b in s["kinds"].items():
            out.append({"supervision": sup, "relation": kind, "queries": b["queries"], "right_pct": dash(b["right_pct"]),
                        "freeform": b["freeform"], "freeform_right_pct": dash(b["freeform_right_pct"]),
                        "miou_visible": dash(b["miou_visible"])})
        out.append({"supervision": sup, "relation": "explicit name (baseline)", "queries": "-", "right_pct": "-",
                    "freeform": "-", "freeform_right_pct": "-", "miou_visible": s["explicit_miou_visible"]})
    seeds = report["seeds"]
    notes = "; ".join(f"{sup}: colour terms right {s['colour_right_pct']}% of {s['colour_objects']}, graph "
                      f"{s['graph_objects']}/{s['objects']} objects, warm query {1000 * s['warm_query_s']:.1f} ms, "
                      f"first {s['first_query_s']:.1f} s" for sup, s in report["supervisions"].items())
    return out, (f"rg synth seeds {seeds[0]}-{seeds[-1]}, {report['objects']} objects ({report.get('same_category', 0)} "
                 f"sharing a category), {report['views']} views; queries "
                 f"unambiguous by {MARGIN} m / 30 %; freeform: hand-written phrasings; mIoU: single-object answers; "
                 f"{notes}")


def add_scene_args(ap) -> None:
    """The scenes' options (also bench_llm_parse's, which asks the same queries)."""
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(411, 421)))
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--same-category", type=int, default=3)
    ap.add_argument("--views", type=int, default=30)


def make_scene(d: Path, seed: int, args) -> Path:
    """`rg synth` scene `seed` as these options ask, in folder d (kept if it exists)."""
    if not d.exists():
        generate_scene(d, SynthConfig(views=args.views, seed=seed, objects=args.objects,
                                      same_category=args.same_category), default_objects_dir(), progress=False)
    return d


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scene_args(ap)
    ap.add_argument("--supervision", nargs="*", default=["oracle", "default"], choices=("oracle", "default"))
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    report = {"seeds": args.seeds, "objects": args.objects, "same_category": args.same_category, "views": args.views,
              "supervisions": {}, "queries": []}
    with tempfile.TemporaryDirectory() as tmp:
        for sup in args.supervision:
            rows, scenes = [], []
            for seed in args.seeds:
                d = make_scene(Path(tmp) / f"seed{seed}", seed, args)
                rs, sc = run_scene(d, seed, sup)
                rows += [{**r, "supervision": sup} for r in rs]
                scenes.append(sc)
                print(f"{sup} seed {seed}: {sum(r['right'] for r in rs)}/{len(rs)} right", file=sys.stderr)
                for r in rs:
                    if not r["right"]:
                        print(f"   wrong ({r['template']}): {r['text']!r} -> {r['got']!r} (expected {r['expect']!r}): "
                              f"{r['explanation']}", file=sys.stderr)
            report["supervisions"][sup] = summarise(rows, scenes)
            report["queries"] += rows
    plt = pyplot()
    fig, axes = plt.subplots(1, len(report["supervisions"]), figsize=(6.5 * len(report["supervisions"]), 3.4),
                             squeeze=False)
    for ax, (sup, s) in zip(axes[0], report["supervisions"].items()):
        ks = list(s["kinds"])
        x = np.arange(len(ks))
        gen = [s["kinds"][k]["right_pct"] or 0 for k in ks]
        free = [s["kinds"][k]["freeform_right_pct"] or 0 for k in ks]
        ax.bar(x - 0.2, gen, 0.4, label="generated")
        ax.bar(x + 0.2, free, 0.4, label="free-form")
        for i, k in enumerate(ks):
            ax.text(i - 0.2, gen[i], f"{s['kinds'][k]['queries']}", ha="center", va="bottom", fontsize=6)
        ax.set_xticks(x, ks, rotation=35, ha="right", fontsize=7)
        ax.set_ylim(0, 115)
        ax.set_ylabel("right target (%)")
        ax.set_title(f"relational queries, {sup} supervision (colour terms {s['colour_right_pct']:.0f}% right)",
                     fontsize=8)
        ax.legend(fontsize=7)
    png = Path(args.out) / "relations.png"
    save_figure(fig, png)
    return finish(args, report, "bench_relations", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
