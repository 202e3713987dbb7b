"""Relational queries generated from a scene's ground truth (Sr3D-style templates, issue 27), each with
the answer it expects: "the object closest to the A", "the object left of the A" (seen from a given
camera), superlatives, colours, ordinals, counting, "all the <category>", and hand-written phrasings
of the same. `rg eval --relational N` asks N of the single-object ones (kind "relational");
benchmarks/bench_relations.py, bench_llm_parse.py and bench_teach.py ask them all."""
from __future__ import annotations

import numpy as np

MARGIN = 0.03          # metres between the expected answer and the runner-up (at least)


def margin(d: float) -> float:
    """How far (m) the runner-up must be behind an expected answer at distance `d`: MARGIN, or the
    answerer's tie share of d where that is more (grounding/relations.py: a tie is no answer, so a
    question whose best two lie within it has none to expect)."""
    from ..grounding.relations import TIE_SHARE

    return max(MARGIN, TIE_SHARE * d)
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
    from ..perception.colour_names import colour_term

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
    from ..grounding.relations import _is_a

    objs = scene.objects
    c = {o.name: (np.asarray(o.aabb_min) + np.asarray(o.aabb_max)) / 2 for o in objs}
    ext = {o.name: np.asarray(o.aabb_max) - np.asarray(o.aabb_min) for o in objs}
    vol = {n: float(np.prod(e)) for n, e in ext.items()}
    names = sorted(c)
    w2c = np.linalg.inv(cam)
    pc = {n: w2c[:3, :3] @ c[n] + w2c[:3, 3] for n in names}
    ux = {n: float(np.arctan2(pc[n][0], pc[n][2])) for n in names}   # bearing from the camera (rad), left to right
    cats = {k: sorted(n for n in names if _is_a(n, k)) for k in CATEGORIES}
    gen: dict[str, list[dict]] = {}

    def add(kind, text, expect, **slots):
        gen.setdefault(kind, []).append({"kind": kind, "text": text, "expect": expect, "slots": slots})

    def nearest(point, pool, exclude):
        d = sorted((float(np.linalg.norm(c[n] - point)), n) for n in pool if n not in exclude)
        return d[0][1] if d and (len(d) == 1 or d[1][0] - d[0][0] >= margin(d[0][0])) else None

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
        if d[1][0] - d[0][0] >= margin(d[0][0]):
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
            if gaps.min() >= 0.05 and all(pc[n][2] > 0 for n in pool):   # "from the left": of things in view
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


def scored_queries(scene, n: int, seed: int = 0) -> list[dict]:
    """Up to n generated relational queries whose answer is one object ({"relation", "text", "expect"}:
    count and "all" queries are left out), taken in turn from each relation kind so that a few cover
    many kinds; asked from the scene's first test camera (view-dependent words refer to it)."""
    if n <= 0 or not scene.test or len(scene.objects) < 2:
        return []
    cam = scene.test[0].cam_to_world
    qs = [q for q in queries(scene, np.random.default_rng(seed), gt_colours(scene), cam, scene.test[0].intrinsics.K)
          if isinstance(q["expect"], str) and q["template"] == "generated"]
    by_kind: dict[str, list[dict]] = {}
    for q in qs:
        by_kind.setdefault(q["kind"], []).append(q)
    out, seen = [], set()
    while len(out) < n and any(by_kind.values()):
        for kind in list(by_kind):
            if by_kind[kind] and len(out) < n:
                q = by_kind[kind].pop(0)
                if q["text"] not in seen:
                    seen.add(q["text"])
                    out.append({"relation": kind, "text": q["text"], "expect": q["expect"]})
    return out
