"""Mapping: error against run time on a synthetic scene, second-pass growth, and a real capture.

    python benchmarks/bench_mapping.py [--scene DIR] [--budgets 5 10 15 30] [--out DIR] [--json] [--record]
                                       [--baseline-code DIR [--seeds 0 1 2]]

Without --scene it generates the `rg synth` default (100 views, 320x240, 7 objects, seed 0).
Writes OUT/mapping_error_vs_time.png and prints one line per run (JSON with --json).

--baseline-code DIR: a checkout of older code with its kernels built (`python setup.py build_ext
--inplace` there); the synthetic scene is mapped with each code's own defaults in fresh processes,
alternating, once per mapper seed (--seeds: PSNR moves by ~0.1 dB between seeds), and the means are
reported with the time ratio.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the code under test: this checkout, or a baseline's (worker processes, --baseline-code)
sys.path.insert(0, os.environ.get("RG_BENCH_CODE") or str(ROOT))
from rg_core.config import MapConfig, SynthConfig  # noqa: E402
from rg_core.io.captures import read_scene  # noqa: E402
from rg_core.eval.mapping import map_scene  # noqa: E402
from rg_core.map.run import stream_frames  # noqa: E402
from rg_core.synth.generator import default_objects_dir, generate_scene  # noqa: E402
from _common import add_output_flags, code_worker, commit_of, finish, pyplot, save_figure  # noqa: E402


def to_rows(report: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: one per synthetic budget, then the real capture (if mapped)."""
    def row(scene: str, rep: dict) -> dict:
        q = rep["test"]
        r = {"scene": scene, "iters_per_keyframe": rep.get("iters_per_keyframe", report["default_iters_per_keyframe"]),
             "time_s": round(rep["seconds_total"], 1), "keyframes": rep["keyframes"], "gaussians": rep["gaussians"],
             "psnr_db": round(q["psnr"], 2), "depth_error_median_mm": round(1000 * q["depth_abs_error_median_m"], 2)}
        if "second_pass" in rep:
            r["second_pass_growth_pct"] = round(100 * rep["second_pass"]["growth"], 2)
        return r

    rows = [row("synthetic 100 views", rep) for rep in report["synthetic"]]
    if report["real"]:
        rows.append(row(Path(report["real_scene"]).name, report["real"]))
    s = report["synthetic"][0]
    notes = (f"320x240 mapping, {s['train_frames']} train / {s['test_frames']} test views (synthetic), "
             f"+{report['final_iters']} final iterations (ceiling); default "
             f"{report['default_iters_per_keyframe']} it/kf; PSNR and depth error on the test views")
    if "baseline" in report:
        b = report["baseline"]
        for name in ("baseline", "new"):
            m = b[name]
            rows.append({"scene": f"synthetic 100 views, {name} defaults", "iters_per_keyframe": m["iters_per_keyframe"],
                         "time_s": m["seconds_mean"], "psnr_db": m["psnr_mean"],
                         "depth_error_median_mm": m["depth_error_median_mm_mean"]})
        notes += (f"; baseline = {b['code']}, each code's own defaults, mean of mapper seeds {b['seeds']}: "
                  f"time ratio baseline / new x{b['speedup']}, PSNR new - baseline {b['psnr_change_db']:+.2f} dB")
    return rows, notes


def map_worker(scene: str, seed: int) -> dict:
    """The scene mapped with this code's defaults and mapper seed `seed` (a fresh process per call)."""
    cfg = dataclasses.replace(MapConfig(), seed=seed)
    _, rep = map_scene(scene, cfg, progress=False)
    return {"seconds": rep["seconds_total"], "psnr": rep["test"]["psnr"], "iters_per_keyframe": cfg.iters_per_keyframe,
            "depth_error_median_mm": 1000 * rep["test"]["depth_abs_error_median_m"], "gaussians": rep["gaussians"]}


def against_baseline(base: Path, scene: str, seeds: list[int]) -> dict:
    """Fresh processes alternating baseline / new code per mapper seed; means and the time ratio."""
    runs = {"baseline": [], "new": []}
    for seed in seeds:
        for name, code in (("baseline", base), ("new", ROOT)):
            runs[name].append(code_worker(__file__, code, [scene, "--worker-seed", str(seed)], 1800, name))
            r = runs[name][-1]
            print(f"{name} seed {seed}: {r['seconds']:.1f} s, PSNR {r['psnr']:.3f} dB", file=sys.stderr)
    out = {"code": f"the code at {commit_of(base)}", "seeds": seeds, "runs": runs}
    for name, rs in runs.items():
        out[name] = {"seconds_mean": round(statistics.mean(r["seconds"] for r in rs), 1),
                     "psnr_mean": round(statistics.mean(r["psnr"] for r in rs), 3),
                     "depth_error_median_mm_mean": round(statistics.mean(r["depth_error_median_mm"] for r in rs), 2),
                     "iters_per_keyframe": rs[0]["iters_per_keyframe"]}
    out["speedup"] = round(out["baseline"]["seconds_mean"] / out["new"]["seconds_mean"], 2)
    out["psnr_change_db"] = round(out["new"]["psnr_mean"] - out["baseline"]["psnr_mean"], 3)
    print(f"baseline / new time x{out['speedup']}, PSNR change {out['psnr_change_db']:+.3f} dB", file=sys.stderr)
    return out


def plot(rows: list[dict], default_budget: int, out_png: Path, baseline: dict | None = None) -> None:
    plt = pyplot()
    secs = [r["seconds_total"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    ax[0].plot(secs, [r["test"]["psnr"] for r in rows], "o-", label="whole image")
    ax[0].plot(secs, [r["test"]["psnr_valid_depth"] for r in rows], "s--", label="valid-depth pixels")
    ax[0].set_xlabel("mapping time (s)")
    ax[0].set_ylabel("test-view PSNR (dB)")
    ax[1].plot(secs, [1000 * r["test"]["depth_abs_error_median_m"] for r in rows], "o-")
    ax[1].set_xlabel("mapping time (s)")
    ax[1].set_ylabel("median |depth error| (mm)")
    for r, s in zip(rows, secs):
        for a, y in ((ax[0], r["test"]["psnr"]), (ax[1], 1000 * r["test"]["depth_abs_error_median_m"])):
            a.annotate(f"{r['iters_per_keyframe']} it" + (" (default)" if r["iters_per_keyframe"] == default_budget else ""),
                       (s, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    if baseline:  # each code's defaults, mean over mapper seeds
        for name, mk in (("baseline", "v"), ("new", "^")):
            m = baseline[name]
            ax[0].plot([m["seconds_mean"]], [m["psnr_mean"]], mk, ms=8, label=f"{name} defaults (mean of seeds)")
            ax[1].plot([m["seconds_mean"]], [m["depth_error_median_mm_mean"]], mk, ms=8)
    ax[0].legend(fontsize=7)
    fig.suptitle("Incremental mapping: error against run time (iterations per keyframe)", fontsize=9)
    save_figure(fig, out_png)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="scene folder (default: generate the rg synth default)")
    ap.add_argument("--budgets", type=int, nargs="+", default=[5, 10, 15, 30])
    ap.add_argument("--real", default=str(Path(__file__).resolve().parents[2] / "shared/data/rgbd/box_toys_50"))
    ap.add_argument("--out", default="bench_out")
    ap.add_argument("--baseline-code", help="checkout of older code (kernels built in place) to compare with")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="mapper seeds of the baseline comparison")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--worker-seed", type=int, default=0, help=argparse.SUPPRESS)
    add_output_flags(ap)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(map_worker(args.worker, args.worker_seed)))
        return 0
    default = MapConfig()
    report = {"default_iters_per_keyframe": default.iters_per_keyframe, "final_iters": default.final_iters,
              "synthetic": [], "real": None}
    with tempfile.TemporaryDirectory() as tmp:
        scene = args.scene
        if scene is None:
            scene = str(Path(tmp) / "synth")
            t = time.perf_counter()
            generate_scene(scene, SynthConfig(), default_objects_dir(), progress=False)
            print(f"generated {scene} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        for it in args.budgets:
            mapper, rep = map_scene(scene, dataclasses.replace(default, iters_per_keyframe=it), progress=False)
            rep["iters_per_keyframe"] = it
            if it == default.iters_per_keyframe:  # stream the same frames again: how much does the map grow?
                n1 = len(mapper.gaussians)
                s2 = stream_frames(mapper, read_scene(scene).train, progress=False)
                rep["second_pass"] = {"growth": round(len(mapper.gaussians) / n1 - 1, 4), "seconds": round(s2, 2),
                                      "keyframes_added": len(mapper.keyframes) - rep["keyframes"]}
            report["synthetic"].append(rep)
            q = rep["test"]
            print(f"synthetic, {it} it/kf: {rep['seconds_total']:.1f} s, {rep['keyframes']} kf, {rep['gaussians']} G, "
                  f"PSNR {q['psnr']:.2f} dB (valid depth {q['psnr_valid_depth']:.2f}), depth median "
                  f"{1000 * q['depth_abs_error_median_m']:.2f} mm, coverage {q['coverage']:.3f}"
                  + (f", second pass growth {100 * rep['second_pass']['growth']:.2f}%" if "second_pass" in rep else ""),
                  file=sys.stderr)
        if args.baseline_code:
            report["baseline"] = against_baseline(Path(args.baseline_code).resolve(), scene, args.seeds)
    if Path(args.real).is_dir():
        _, rep = map_scene(args.real, default, progress=False)
        report["real"], report["real_scene"] = rep, args.real
        q = rep["test"]
        print(f"{Path(args.real).name}: {rep['seconds_total']:.1f} s, {rep['keyframes']} kf, {rep['gaussians']} G, "
              f"PSNR {q['psnr']:.2f} dB (valid depth {q['psnr_valid_depth']:.2f}), depth median "
              f"{1000 * q['depth_abs_error_median_m']:.2f} mm", file=sys.stderr)
    png = Path(args.out) / "mapping_error_vs_time.png"
    plot(report["synthetic"], default.iters_per_keyframe, png, report.get("baseline"))
    report["plot"] = str(png)
    print(f"plot: {png}", file=sys.stderr)
    return finish(args, report, "bench_mapping", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
