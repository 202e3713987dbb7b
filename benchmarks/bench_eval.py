"""The headline figures: `rg eval` with every default, on the default synthetic table top and on real
YCB-Video, with ground-truth 2D inputs (oracle) and with the offline default models.

    python benchmarks/bench_eval.py [--seeds 0] [--ycbv ../shared/data/rgbd/ycbv_0002_bop] [--out DIR] [--json] [--record]

- Synthetic: `rg synth` with its defaults (100 views 320x240, 7 objects) for each seed; real: the
  YCB-Video scene in BOP layout (17 train / 3 test views).
- Each scene: `rg eval SCENE --supervision oracle` and `--supervision default` (each maps, supervises,
  trains the field until it converges, then asks every explicit query and the first implicit one
  per object on every test view). Rows: explicit visible mIoU as rendered and following each test
  view's depth and colour (what the node streams), amodal, localization, implicit visible, boxes with
  IoU >= 0.5, field steps and what stopped it (converged, or its seconds ceiling on a
  loaded CPU), median query seconds, wall seconds; on the synthetic scenes also the paper's ablation
  (`rg eval --ablation`: relevancy > 0.5 alone, with the reasoner's target, with grouping).
Every step runs as its own `rg` process, one after the other. Writes OUT/eval.json (the rows).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _common import add_output_flags, finish, rg_json as rg  # noqa: E402


def eval_row(name: str, scene: Path, supervision: str, ablation: bool = False) -> dict:
    e = rg("eval", str(scene), "--supervision", supervision, *(("--ablation",) if ablation else ()))
    ev, ex, im = e["eval"], e["eval"]["explicit"], e["eval"]["implicit"]
    boxes = ev["box_iou"]["per_object"]
    field = e.get("field") or {}
    row = {"scene": name, "supervision": supervision, "field_steps": field.get("steps"),
           "field_stop": (field.get("stop") or {}).get("stopped"),   # "seconds": the CPU's load cut it short
           "explicit_visible_miou": ex["miou_visible"], "explicit_visible_depth_miou": ex.get("miou_visible_depth"),
           "explicit_amodal_miou": ex.get("miou_amodal"), "localization_pct": ex.get("localization"),
           "implicit_visible_miou": im.get("miou_visible"),
           "boxes_iou_half_or_more": f"{sum(v >= 0.5 for v in boxes.values())} of {len(boxes)}",
           "query_median_s": ev["seconds"]["per_query_median"], "eval_wall_s": e["wall_s"],
           "gaussians": (e.get("map") or {}).get("gaussians"),
           "worst_object": min(((v.get("explicit", v)["miou_visible_depth"], k) for k, v in ev["per_object"].items()),
                               default=(None, ""))[1]}
    if ablation:   # the paper's ablation: relevancy > 0.5 alone (visible), + the reasoner's target, + grouping (amodal)
        ab = ev["ablation"]
        row.update(relevancy_only_miou=ab["relevancy_only"]["miou"], with_reasoning_miou=ab["with_reasoning"]["miou"],
                   with_grouping_amodal_miou=ab["with_grouping_amodal"]["miou"])
    print(row, file=sys.stderr)
    return row


def to_rows(report: dict) -> tuple[list[dict], str]:
    def num(v):   # nan (YCB-Video has no amodal masks) and None are not numbers a table can hold
        return "-" if v is None or v != v else v

    rows = [{k: num(v) for k, v in r.items()} for r in report["rows"]]
    seeds = ", ".join(str(s) for s in report["seeds"])
    return rows, (f"rg synth defaults (100 views 320x240, 7 objects; seed {seeds}) and {report['ycbv']} (real, 17 train "
                  "/ 3 test views); rg eval with every default, oracle = ground-truth 2D masks and names, default = the "
                  "offline models; visible depth: masks following each test view's depth and colour images")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0], help="rg synth seeds (0: its default scene)")
    ap.add_argument("--ycbv", default=str(ROOT.parent / "shared" / "data" / "rgbd" / "ycbv_0002_bop"),
                    help='a YCB-Video scene in BOP layout ("none": skip)')
    ap.add_argument("--supervision", nargs="+", default=["oracle", "default"], choices=("oracle", "default"))
    ap.add_argument("--out", default="bench_out", help="where the report JSON goes")
    add_output_flags(ap)
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_eval ") as tmp:
        work = Path(tmp)
        for seed in args.seeds:
            scene = work / f"synth_{seed}"
            rg("synth", str(scene), "--seed", str(seed))
            rows += [eval_row(f"synthetic, seed {seed}", scene, s, ablation=True) for s in args.supervision]
        if args.ycbv != "none":
            rows += [eval_row(Path(args.ycbv).name, Path(args.ycbv), s) for s in args.supervision]
    report = {"seeds": args.seeds, "ycbv": Path(args.ycbv).name, "rows": rows}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "eval.json").write_text(json.dumps(report, indent=1))
    return finish(args, report, "bench_eval", to_rows)


if __name__ == "__main__":
    raise SystemExit(main())
