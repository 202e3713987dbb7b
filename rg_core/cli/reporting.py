"""`rg report` (error against run time, savings, scaling, stability as report.md + PNGs) and
`rg demo` (the main job on an embedded default scene): both run rg_core.report."""
from __future__ import annotations

from pathlib import Path

from .config_args import add_sections
from .options import add_common, floats, size


def cmd_report(args, cfg) -> dict:
    from ..report import SECTIONS, full_budgets, tiny_budgets
    from ..report.runner import run_report

    over = {}
    if args.map_iters:
        over["map_iters"] = tuple(int(v) for v in args.map_iters)
    if args.field_seconds:
        over["field_seconds"] = args.field_seconds
    if args.frames:
        over["frames"] = tuple(int(v) for v in args.frames)
    if args.sizes:
        over["sizes"] = tuple(size(v) for v in args.sizes.split(","))
    budgets = (tiny_budgets if args.tiny else full_budgets)(**over)
    sections = tuple(args.sections.split(",")) if args.sections else SECTIONS
    rep = run_report(args.scene, args.out, budgets, sections, cfg, progress=not args.quiet,
                     budgets_name="tiny" if args.tiny else "full")
    return {"report": str(Path(args.out) / "report.md"), "seconds": round(rep["seconds"], 1),
            "recommendations": rep["recommendations"], "headline": rep["headline"],
            "failed_sections": [k for k, v in rep["sections"].items() if "error" in v]}


def cmd_demo(args, cfg) -> dict:
    from ..report.demo import run_demo

    return run_demo(cfg, Path(args.out), progress=not args.quiet)


def _demo_human(result: dict) -> str:
    from ..viz.summary import demo_summary

    return demo_summary(result)


def add_report(sub) -> None:
    p = sub.add_parser("report", help="error against run time, savings, scaling, stability: DIR/report.md + PNGs")
    p.add_argument("scene", help="ReasoningGD scene folder (objects.json and queries.json for grounding) or BOP scene; "
                                  "photos without depth: the mapping section plots the photo fit's held-out PSNR "
                                  "against time")
    p.add_argument("--out", required=True, help="output folder (report.md, report.json, plots/)")
    p.add_argument("--tiny", action="store_true", help="seconds-long budgets (what the test suite runs)")
    p.add_argument("--sections", help="comma-separated subset of mapping,grounding,latency,memory,savings,"
                                      "scaling,stability,degraded (default: all)")
    # The budgets the report sweeps, not config fields.
    p.add_argument("--map-iters", type=floats, help="iterations per keyframe of the mapping section, e.g. 5,15,30")
    p.add_argument("--field-seconds", type=floats, help="feature-training budgets, e.g. 10,20,40,80")
    p.add_argument("--frames", type=floats, help="frame counts of the scaling, e.g. 25,50,100,200")
    p.add_argument("--sizes", help="image sizes of the scaling, e.g. 160x120,320x240,640x480")
    add_common(p)
    add_sections(p, ("map", "photo", "field", "ground", "reason", "models"))
    p.set_defaults(func=cmd_report)


def add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the main job on an embedded default scene")
    p.add_argument("--out", default="rg_demo", help="output folder (default: ./rg_demo)")
    add_common(p)
    # demo.* sets the scene's views, size, objects and seed; synth.* the rest of the generator.
    add_sections(p, ("demo", "synth", "map", "field", "ground", "reason", "models"))
    p.set_defaults(func=cmd_demo, human=_demo_human)
