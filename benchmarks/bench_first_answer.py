"""Frames to first answer: `rg eval`'s seconds_build (map + supervision + field, i.e. frames to a
queryable field) and explicit visible mIoU, this code against an older checkout, in one run.

    python benchmarks/bench_first_answer.py --baseline-code DIR [--seeds 23 31] [--views 30]
        [--bop ../shared/data/rgbd/ycbv_0002_bop] [--supervision default oracle] [--out DIR] [--json] [--record]

Each scene (`rg synth` with each seed, 320x240, 7 objects; and the BOP scene) and supervision is
evaluated by both codes with their own defaults, in fresh processes, baseline first; the ratio
baseline / new of seconds_build is the speed-up. DIR is a checkout with its kernels built
(`python setup.py build_ext --inplace` there). Writes OUT/first_answer.png.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from rg_core.config import SynthConfig  # noqa: E402
from rg_core.synth.generator import default_objects_dir, generate_scene  # noqa: E402
from _common import add_output_flags, commit_of, finish, pyplot, save_figure  # noqa: E402

RUN = "import sys; sys.path.insert(0, sys.argv.pop(1)); from rg_core.cli import main; sys.exit(main(sys.argv[1:]))"


def rg_eval(code: Path, scene: str, supervision: str) -> dict:
    """`rg eval SCENE --supervision S --json` with the code in `code`, in a fresh process."""
    env = dict(os.environ, HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1")
    res = subprocess.run([sys.executable, "-c", RUN, str(code), "eval", scene, "--supervision", supervision,
                          "--json", "--quiet"], env=env, capture_output=True, text=True, timeout=3600)
    if res.returncode != 0:
        raise RuntimeError(f"rg eval ({code}) failed on {scene}: {res.stderr[-2000:]}")
    d = json.loads(res.stdout.strip().splitlines()[-1])
    e = d["eval"]
    return {"seconds_build": d["seconds_build"], "seconds_map": d.get("seconds_map"),
            "field_steps": (d.get("field") or {}).get("steps"), "explicit_visible": e["explicit"]["miou_visible"],
            "explicit_amodal": e["explicit"]["miou_amodal"], "implicit_visible": e["implicit"]["miou_visible"]}


def to_rows(report: dict) -> tuple[list[dict], str]:
    rows = [{"scene": r["scene"], "supervision": r["supervision"], "baseline_s": round(r["baseline"]["seconds_build"], 1),
             "new_s": round(r["new"]["seconds_build"], 1), "speedup": f"x{r['speedup']}",
             "explicit_visible_baseline": r["baseline"]["explicit_visible"],
             "explicit_visible_new": r["new"]["explicit_visible"], "explicit_visible_change": r["miou_change"]}
            for r in report["runs"]]
    return rows, (f"rg eval seconds_build (frames to a queryable field) and explicit visible mIoU; baseline = "
                  f"the code at {report['baseline_commit']} with its own defaults; rg synth scenes {report['views']} views 320x240, "
                  "7 objects; fresh processes, baseline first")


def plot(report: dict, png: Path) -> None:
    plt = pyplot()
    runs = report["runs"]
    fig, ax = plt.subplots(figsize=(1.6 * len(runs) + 2, 3.6))
    xs = range(len(runs))
    for i, (name, off) in enumerate((("baseline", -0.2), ("new", 0.2))):
        vals = [r[name]["seconds_build"] for r in runs]
        ax.bar([x + off for x in xs], vals, width=0.38, label=name)
        for x, r, v in zip(xs, runs, vals):
            ax.text(x + off, v, f"{v:.0f} s\n{r[name]['explicit_visible']:.1f}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(list(xs), [f"{r['scene']}\n{r['supervision']}\nx{r['speedup']}" for r in runs], fontsize=7)
    ax.set_ylabel("frames to a queryable field (s)")
    ax.set_ylim(0, 1.25 * max(r["baseline"]["seconds_build"] for r in runs))
    ax.legend(fontsize=8)
    ax.set_title("rg eval: seconds_build (bars) and explicit visible mIoU (under each label)", fontsize=9)
    save_figure(fig, png)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline-code", required=True, help="checkout of older code (kernels built in place)")
    ap.add_argument("--seeds", type=int, nargs="*", default=[23, 31], help="rg synth seeds of the synthetic scenes")
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--bop", default=str(ROOT.parent / "shared/data/rgbd/ycbv_0002_bop"), help="a BOP scene ('' : none)")
    ap.add_argument("--supervision", nargs="+", default=["default", "oracle"], choices=["default", "oracle"])
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    base = Path(args.baseline_code).resolve()
    report = {"baseline_code": str(base), "baseline_commit": commit_of(base), "views": args.views, "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        scenes = []
        for seed in args.seeds:
            d = Path(tmp) / f"synth_seed{seed}"
            generate_scene(d, SynthConfig(views=args.views, seed=seed), default_objects_dir(), progress=False)
            scenes.append((f"synth seed {seed}", str(d)))
        if args.bop and Path(args.bop).is_dir():
            scenes.append((Path(args.bop).name, args.bop))
        for name, scene in scenes:
            for sup in args.supervision:
                b, n = rg_eval(base, scene, sup), rg_eval(ROOT, scene, sup)
                r = {"scene": name, "supervision": sup, "baseline": b, "new": n,
                     "speedup": round(b["seconds_build"] / n["seconds_build"], 2),
                     "miou_change": round(n["explicit_visible"] - b["explicit_visible"], 2)}
                report["runs"].append(r)
                print(f"{name}, {sup}: {b['seconds_build']:.1f} -> {n['seconds_build']:.1f} s (x{r['speedup']}), "
                      f"explicit visible {b['explicit_visible']:.2f} -> {n['explicit_visible']:.2f}", file=sys.stderr)
    png = Path(args.out) / "first_answer.png"
    plot(report, png)
    print(f"plot: {png}", file=sys.stderr)
    return finish(args, report, "bench_first_answer", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
