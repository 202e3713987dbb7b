"""`rg report` on the standard synthetic scene: prints the headline figures (JSON with --json).

    python benchmarks/bench_report.py [--scene DIR] [--out bench_out/report] [--sections a,b] [--tiny] [--json]
                                      [--record]

Without --scene it generates (once) bench_out/report_scene: 40 views, 320x240, 7 objects, seed 0
(`rg synth bench_out/report_scene --views 40 --size 320x240 --seed 0 --objects 7`). Writes
OUT/report.md, OUT/report.json and OUT/plots/*.png. The full run takes 20-30 min on 2 cores.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from rg_core.config import SynthConfig  # noqa: E402
from rg_core.report import SECTIONS, full_budgets, tiny_budgets  # noqa: E402
from rg_core.report.runner import run_report  # noqa: E402
from rg_core.synth.generator import default_objects_dir, generate_scene  # noqa: E402
from _common import add_output_flags, finish  # noqa: E402


def to_rows(out: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: one per report section (its status and table size); the figures stay in
    report.md, whose tables are too wide for one short row each."""
    rows = []
    for name, h in out["headline"].items():
        err = isinstance(h, dict) and "error" in h
        rows.append({"section": name, "status": f"error: {h['error']}"[:48] if err else "ok",
                     "table_rows": 0 if err else len(h)})
    return rows, f"report {out['report']} ({out['seconds']} s); figures in its tables and plots"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="scene folder (default: generate bench_out/report_scene)")
    ap.add_argument("--out", default="bench_out/report")
    ap.add_argument("--sections", default=",".join(SECTIONS))
    ap.add_argument("--tiny", action="store_true", help="seconds-long budgets")
    add_output_flags(ap)
    args = ap.parse_args()
    scene = Path(args.scene or "bench_out/report_scene")
    if args.scene is None and not (scene / "transforms_train.json").is_file():
        generate_scene(scene, SynthConfig(views=40, width=320, height=240, objects=7, seed=0), default_objects_dir(),
                       progress=True)
    budgets = tiny_budgets() if args.tiny else full_budgets()
    rep = run_report(scene, args.out, budgets, tuple(args.sections.split(",")), budgets_name="tiny" if args.tiny else "full")
    out = {"report": str(Path(args.out) / "report.md"), "machine": rep["machine"], "seconds": round(rep["seconds"], 1),
           "recommendations": rep["recommendations"], "headline": rep["headline"]}
    print(f"report: {out['report']} ({out['seconds']} s)", file=sys.stderr)
    for r in rep["recommendations"]:
        print(r, file=sys.stderr)
    return finish(args, out, "bench_report", to_rows)


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
