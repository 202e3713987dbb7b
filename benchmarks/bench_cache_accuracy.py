"""Accuracy with and without the Grounder's map caches (issue 17: warm queries got faster by caching
what depends only on the map; the answers must stay the same within 1 mIoU point).

    python benchmarks/bench_cache_accuracy.py [--seed 23] [--views 24] [--objects 5] [--field-iters 300]
                                              [--supervision oracle] [--out DIR] [--record]

One synthetic scene (a seed the team never tuned on by default), one map and one trained field
(trained by step count, so the field is the same whatever the machine's load), then every query of
`rg eval` (explicit + first implicit per object, every test view) asked through a Grounder with
the caches on (the default) and through one with them off (cache=False, the code path before
the caches), on the same map and field, in the same process. Prints and writes
OUT/cache_accuracy.json: visible / amodal mIoU, localization, box IoU and seconds per query of both,
and the differences.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rg_core.util import run_json_script  # noqa: E402
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import add_output_flags, finish  # noqa: E402

KEYS = ("miou_visible", "miou_amodal", "localization", "target_accuracy")


def _pick(summary: dict) -> dict:
    out = {kind: {k: (summary.get(kind) or {}).get(k) for k in KEYS + ("pairs",)} for kind in ("explicit", "implicit")}
    out["box_iou_per_object"] = summary["box_iou"]["per_object"]
    out["seconds_per_query_median"] = summary["seconds"]["per_query_median"]
    return out


def to_rows(res: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: caches on and off, explicit and implicit mIoU, median query time."""
    rows = []
    for name in ("cache_on", "cache_off"):
        r = res[name]
        pct = lambda kind, k: round(r[kind][k], 2) if r[kind].get(k) is not None else "-"   # already 0-100
        rows.append({"grounder": name.replace("_", " "), "explicit_visible_miou": pct("explicit", "miou_visible"),
                     "explicit_amodal_miou": pct("explicit", "miou_amodal"),
                     "localization_pct": pct("explicit", "localization"),
                     "implicit_visible_miou": pct("implicit", "miou_visible"),
                     "query_median_s": round(r["seconds_per_query_median"], 3)})
    d = res["difference_on_minus_off"]["explicit"].get("miou_visible")
    sc = res["scene"]
    return rows, (f"rg synth {sc['views']} views, {sc['objects']} objects, seed {sc['seed']}; {res['supervision']} "
                  f"supervision, {res['gaussians']} Gaussians, field {res['field_steps']} steps by count; explicit "
                  f"visible difference on - off {d:.2f} points (target: within 1)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--objects", type=int, default=5)
    ap.add_argument("--field-iters", type=int, default=300)
    ap.add_argument("--supervision", default="oracle", choices=("oracle", "default"))
    ap.add_argument("--out", default=str(ROOT / "bench_out" / "cache_accuracy"))
    add_output_flags(ap, json_flag=False)
    a = ap.parse_args(argv)
    from rg_core.config import RGConfig, SynthConfig
    from rg_core.eval.grounding import evaluate_queries
    from rg_core.grounding.build import build_grounder
    from rg_core.grounding.pipeline import Grounder
    from rg_core.io.captures import read_scene
    from rg_core.synth.generator import default_objects_dir, generate_scene

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = RGConfig()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        generate_scene(Path(tmp) / "scene", SynthConfig(views=a.views, objects=a.objects, seed=a.seed),
                       default_objects_dir())
        scene = read_scene(Path(tmp) / "scene")
        t_synth = time.perf_counter() - t
        g_on, rep = build_grounder(scene, cfg, supervision=a.supervision, field_seconds=0)
        g_on.field.train(iters=a.field_iters)
        g_off = Grounder(g_on.mapper, g_on.field, cfg, reasoner=g_on.reasoner, text_encoder=g_on._text,
                         scene_names=g_on.scene_names, cache=False)
        res = {"scene": {"seed": a.seed, "views": a.views, "objects": a.objects, "synth_s": round(t_synth, 1)},
               "gaussians": len(g_on.mapper.gaussians), "field_steps": g_on.field.steps,
               "supervision": a.supervision}
        for name, g in (("cache_on", g_on), ("cache_off", g_off)):
            t = time.perf_counter()
            res[name] = _pick(evaluate_queries(g, scene, progress=True))
            res[name]["eval_s"] = round(time.perf_counter() - t, 1)
    res["difference_on_minus_off"] = {
        kind: {k: round(res["cache_on"][kind][k] - res["cache_off"][kind][k], 4)
               for k in KEYS if res["cache_on"][kind].get(k) is not None and res["cache_off"][kind].get(k) is not None}
        for kind in ("explicit", "implicit")}
    (out / "cache_accuracy.json").write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))
    return finish(a, res, "bench_cache_accuracy", to_rows)


if __name__ == "__main__":
    run_json_script(main)
