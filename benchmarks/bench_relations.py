"""Relational queries (issue 27): right-target rate per relation type on synthetic scenes, queries
generated from the ground truth where the answer is unambiguous by a stated margin.

    python benchmarks/bench_relations.py [--seeds 301 302 ...] [--objects 9] [--views 30] [--json] [--record]

Each scene (`rg synth`, 320x240) is mapped with oracle supervision (the 3D part; default supervision
names objects wrongly, see bench_confidence) and asked, from its first test camera:
- near: "the object closest to the A" for every A whose nearest and second-nearest neighbours
  (object centres) differ by >= MARGIN;
- between: "the object between the A and the B", nearest to the midpoint by >= MARGIN (3 per scene);
- superlative: "the biggest / smallest object" when the first and second box volumes differ by >= 30 %;
- left / right: "the object left of the A" seen from the camera, nearest to A among those on that
  side by >= MARGIN (2 per scene and side);
- count: "how many cups are there" (every cup; when the scene has one) and "how many A are there".
Right = the answer's target is the expected object (count: the right number). Writes relations.png.
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

MARGIN = 0.03   # metres between the expected answer and the runner-up


def queries(scene, rng) -> list[dict]:
    """(kind, text, expected target name or count) from the scene's ground truth."""
    objs = scene.objects
    c = {o.name: (np.asarray(o.aabb_min) + np.asarray(o.aabb_max)) / 2 for o in objs}
    vol = {o.name: float(np.prod(np.asarray(o.aabb_max) - np.asarray(o.aabb_min))) for o in objs}
    names = sorted(c)
    out = []

    def nearest(point, exclude):
        d = sorted((float(np.linalg.norm(c[n] - point)), n) for n in names if n not in exclude)
        return d[0][1] if len(d) > 1 and d[1][0] - d[0][0] >= MARGIN else None

    for a in names:
        e = nearest(c[a], {a})
        if e:
            out.append({"kind": "near", "text": f"the object closest to the {a}", "expect": e})
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    rng.shuffle(pairs)
    n = 0
    for a, b in pairs:
        e = nearest((c[a] + c[b]) / 2, {a, b})
        if e and n < 3:
            out.append({"kind": "between", "text": f"the object between the {a} and the {b}", "expect": e})
            n += 1
    by_vol = sorted(names, key=lambda k: vol[k])
    if vol[by_vol[-1]] >= 1.3 * vol[by_vol[-2]]:
        out.append({"kind": "superlative", "text": "the biggest object", "expect": by_vol[-1]})
    if vol[by_vol[1]] >= 1.3 * vol[by_vol[0]]:
        out.append({"kind": "superlative", "text": "the smallest object", "expect": by_vol[0]})
    w2c = np.linalg.inv(scene.test[0].cam_to_world)
    x = {n: float((w2c[:3, :3] @ c[n] + w2c[:3, 3])[0]) for n in names}
    for side, test in (("left", lambda n, a: x[n] < x[a]), ("right", lambda n, a: x[n] > x[a])):
        k = 0
        for a in rng.permutation(names):
            on = [n for n in names if n != a and test(n, a)]
            d = sorted((float(np.linalg.norm(c[n] - c[a])), n) for n in on)
            if d and (len(d) == 1 or d[1][0] - d[0][0] >= MARGIN) and k < 2:
                out.append({"kind": side, "text": f"the object {side} of the {a}", "expect": d[0][1]})
                k += 1
    cups = [n for n in names if n == "cup" or n.endswith(" cup")]
    if cups:
        out.append({"kind": "count", "text": "how many cups are there", "expect": len(cups)})
    a = names[int(rng.integers(len(names)))]
    out.append({"kind": "count", "text": f"how many {a if a.endswith('s') else a + 's'} are there", "expect": 1})
    return out


def run_scene(path: Path, seed: int) -> list[dict]:
    from rg_core.grounding.build import build_grounder
    from rg_core.io.captures import read_scene

    scene = read_scene(path)
    g, _ = build_grounder(scene, RGConfig(), "oracle")
    cam = scene.test[0].cam_to_world
    rows = []
    for i, q in enumerate(queries(scene, np.random.default_rng(seed))):
        t = time.perf_counter()
        r = g.ground(q["text"], cam_to_world=cam)
        dt = time.perf_counter() - t
        got = len(r.objects) if q["kind"] == "count" and r.success else r.target
        rows.append({**q, "scene": seed, "got": got, "right": bool(r.success and got == q["expect"]), "seconds": dt,
                     "first": i == 0, "explanation": r.explanation or r.message})
    return rows


def to_rows(report: dict) -> tuple[list[dict], str]:
    out = []
    for kind, b in report["kinds"].items():
        out.append({"relation": kind, "queries": b["queries"], "right_pct": b["right_pct"]})
    return out, (f"rg synth seeds {' '.join(map(str, report['seeds']))}, {report['objects']} objects, "
                 f"{report['views']} views 320x240, oracle supervision, queries generated from the ground truth "
                 f"(margin {MARGIN} m); warm query median {report['warm_query_s']:.3f} s, first query (builds the "
                 f"scene graph) median {report['first_query_s']:.1f} s")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(301, 311)))
    ap.add_argument("--objects", type=int, default=9)
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            d = Path(tmp) / f"seed{seed}"
            generate_scene(d, SynthConfig(views=args.views, seed=seed, objects=args.objects), default_objects_dir(),
                           progress=False)
            rs = run_scene(d, seed)
            rows += rs
            print(f"seed {seed}: {sum(r['right'] for r in rs)}/{len(rs)} right", file=sys.stderr)
            for r in rs:
                if not r["right"]:
                    print(f"   wrong: {r['text']!r} -> {r['got']!r} (expected {r['expect']!r}): {r['explanation']}",
                          file=sys.stderr)
    kinds = {}
    for k in sorted({r["kind"] for r in rows}) + ["all"]:
        rs = [r for r in rows if k == "all" or r["kind"] == k]
        kinds[k] = {"queries": len(rs), "right_pct": round(100 * float(np.mean([r["right"] for r in rs])), 1)}
    report = {"seeds": args.seeds, "objects": args.objects, "views": args.views, "kinds": kinds, "queries": rows,
              "warm_query_s": float(np.median([r["seconds"] for r in rows if not r["first"]])),
              "first_query_s": float(np.median([r["seconds"] for r in rows if r["first"]]))}
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ks = list(kinds)
    ax.bar(ks, [kinds[k]["right_pct"] for k in ks])
    for i, k in enumerate(ks):
        ax.text(i, kinds[k]["right_pct"], f"{kinds[k]['right_pct']:.0f}%\n(n={kinds[k]['queries']})", ha="center",
                va="bottom", fontsize=7)
    ax.set_ylim(0, 115)
    ax.set_ylabel("right target (%)")
    ax.set_title("relational queries, oracle supervision", fontsize=9)
    png = Path(args.out) / "relations.png"
    save_figure(fig, png)
    return finish(args, report, "bench_relations", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
