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

# The generator lives in rg_core/eval/relational.py (rg eval --relational asks its queries too); its
# names stay importable from here for bench_llm_parse and bench_teach.
from rg_core.eval.relational import (CATEGORIES, FREEFORM, MARGIN, ORDINAL, _plural, freeform,  # noqa: E402,F401
                                     gt_colours, queries, what_it_got)


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
