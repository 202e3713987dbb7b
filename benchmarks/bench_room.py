"""Room scale (issue 28): a synthetic room and a real kitchen mapped, then asked, on a 2-core CPU.

    python benchmarks/bench_room.py [--seed 501] [--objects 40] [--views 320] [--tables 4] [--more-seeds 502 503]
                                    [--kitchen ../shared/data/rgbd/redkitchen_100] [--json] [--record]

- Synthetic room: `rg synth --layout room` (4 tables 3 m apart, the objects shared among them, a camera
  walk from table to table at head height, 320x240), the same room walked close to the tables
  (`synth.room_radius` 0.45-0.7 m: objects as large in the image as on the table top, whose ring is
  0.38-0.62 m), the room mapped with `map.seed_spacing` (far surfaces seeded at half the stride),
  and the same seed as one table-top scene
  (`rg synth`, 7 objects, 100 views) for the reference figure. Each: `rg map` (Gaussians, keyframes,
  seconds, peak RSS, test PSNR) and `rg eval --map` of that map with oracle supervision (explicit /
  implicit visible mIoU, and explicit with masks sharpened by each test view's depth and colour
  images, labelled "depth"; first_answer_s: supervision and field training on the built map). Target: the room's explicit mIoU within 5 points
  of the table top's.
- --more-seeds: for each, its table top and head-height room again (the gap is one figure per seed).
- --hires WxH (default 640x480, "none" skips): the table top and head-height room of --seed rendered at
  that size and mapped at its width (`map.width`): the gap at a Kinect's resolution, and its cost.
- 7-Scenes redkitchen_100 (real Kinect, every 10th frame of a room-scale sequence): `rg map` alone
  (no object ground truth).
Every step runs as its own `rg` process, one after the other. Writes room.png (seconds and peak RSS
per step, mIoU of the two synthetic scenes).
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _common import add_output_flags, finish, rg_json as rg, pyplot, save_figure  # noqa: E402


def scene_rows(name: str, scene: Path, work: Path, oracle: bool, config: Path | None = None) -> dict:
    cfg = ("--config", str(config)) if config else ()
    m = rg(*cfg, "map", str(scene), "--out", str(work / f"{name}.rgmap"))
    row = {"scene": name, "frames": m["train_frames"], "keyframes": m["keyframes"], "gaussians": m["gaussians"],
           "map_s": m["seconds_total"], "peak_rss_mb": m["peak_rss_mb"], "test_psnr_db": m["test"]["psnr"],
           "depth_err_median_mm": round(1000 * m["test"]["depth_abs_error_median_m"], 1)}
    if oracle:
        e = rg(*cfg, "eval", str(scene), "--map", str(work / f"{name}.rgmap"), "--supervision", "oracle")
        ev = e["eval"]
        row.update(explicit_miou_visible=ev["explicit"]["miou_visible"], implicit_miou_visible=ev["implicit"]["miou_visible"],
                   explicit_miou_visible_depth=ev["explicit"].get("miou_visible_depth"),
                   explicit_target_pct=ev["explicit"]["target_accuracy"], first_answer_s=e["seconds_build"],
                   eval_wall_s=e["wall_s"], objects=len(ev["per_object"]))
    print(row, file=sys.stderr)
    return row


def to_rows(report: dict) -> tuple[list[dict], str]:
    rows = [{k: v for k, v in r.items() if v is not None} for r in report["rows"]]
    def table_of(scene: str) -> dict:   # the table top of the same seed and size
        tag = re.search(r", (seed \d+|\d+x\d+)$", scene)
        return next(r for r in report["rows"] if r["scene"] == ("table top" if tag is None else f"table top, {tag.group(1)}"))

    def gap(r: dict) -> str:   # rendered masks / sharpened by the view's depth (records before have none)
        t, k = table_of(r["scene"]), "explicit_miou_visible_depth"
        d = f"/{t[k] - r[k]:.1f}" if r.get(k) is not None and t.get(k) is not None else ""
        return f"{t['explicit_miou_visible'] - r['explicit_miou_visible']:.1f}{d}"
    lo, hi = report.get("close_radius", (0.45, 0.7))
    more = "".join(f", {x}" for x in report.get("more_seeds", []))
    label = lambda k: k.replace("synthetic room, ", "").replace("synthetic room", "room")
    hi_res = report.get("hires", "none")
    return rows, (f"rg synth seeds {report['seed']}{more}: {report['objects']} objects on {report['tables']} tables, "
                  f"{report['views']} views, 0.9-1.3 m from a table (room), {lo:g}-{hi:g} m (close), 0.38-0.62 m "
                  f"(table top: 7 objects, {report['table_views']} views); seed spacing {report.get('seed_spacing', 0.015):g} m"
                  + ("" if hi_res == "none" else f"; {hi_res} mapped at it")
                  + "; oracle. Explicit mIoU below the table top (same seed, size), rendered/depth masks: "
                  + ", ".join(f"{label(r['scene'])} {gap(r)}" for r in report["rows"] if r["scene"].startswith("synthetic room"))
                  + " (target 5)")


def plot(report: dict, png: Path) -> Path:
    plt = pyplot()
    rows = report["rows"]
    fig, ax = plt.subplots(1, 3, figsize=(12, 4.2))
    names = [r["scene"] for r in rows]
    ax[0].bar(names, [r["map_s"] for r in rows])
    ax[0].set_ylabel("rg map seconds")
    ax[1].bar(names, [r["peak_rss_mb"] for r in rows])
    ax[1].set_ylabel("rg map peak RSS (MB)")
    syn = [r for r in rows if "explicit_miou_visible" in r]
    x = range(len(syn))
    ax[2].bar([i - 0.27 for i in x], [r["explicit_miou_visible"] for r in syn], 0.27, label="explicit")
    ax[2].bar(list(x), [r.get("explicit_miou_visible_depth") or 0.0 for r in syn], 0.27,
              label="explicit, masks with the view's depth")
    ax[2].bar([i + 0.27 for i in x], [r["implicit_miou_visible"] for r in syn], 0.27, label="implicit")
    ax[2].set_xticks(list(x), [r["scene"] for r in syn])
    ax[2].set_ylabel("visible mIoU, oracle")
    ax[2].legend(fontsize=7)
    for a in ax:
        a.tick_params(axis="x", labelsize=7, labelrotation=30)
        for t in a.get_xticklabels():
            t.set_horizontalalignment("right")
    fig.suptitle(f"room scale: {report['objects']} objects, {report['views']} views", fontsize=9)
    save_figure(fig, png)
    return png


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=501)
    ap.add_argument("--objects", type=int, default=40)
    ap.add_argument("--views", type=int, default=320)
    ap.add_argument("--tables", type=int, default=4)
    ap.add_argument("--table-views", type=int, default=100, help="views of the table-top reference scene")
    ap.add_argument("--close-radius", type=float, nargs=2, default=(0.45, 0.7),
                    help="the second room's walk: distance from each table's centre (m)")
    ap.add_argument("--seed-spacing", type=float, default=0.015,
                    help="map.seed_spacing (m) of the room's third row: far surfaces seeded at half the stride")
    ap.add_argument("--more-seeds", type=int, nargs="*", default=[],
                    help="further rg synth seeds: each adds its table top and head-height room (the gap per seed)")
    ap.add_argument("--hires", default="640x480",
                    help='WxH of a further table top and room of --seed, mapped at that width ("none": skip)')
    ap.add_argument("--kitchen", default=str(ROOT.parent / "shared" / "data" / "rgbd" / "redkitchen_100"))
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        room = rg("synth", str(work / "room"), "--layout", "room", "--objects", str(args.objects), "--tables",
                  str(args.tables), "--views", str(args.views), "--seed", str(args.seed))
        close = work / "close.yaml"
        close.write_text(f"synth:\n  room_radius: [{args.close_radius[0]}, {args.close_radius[1]}]\n")
        rg("--config", str(close), "synth", str(work / "room_close"), "--layout", "room", "--objects", str(args.objects),
           "--tables", str(args.tables), "--views", str(args.views), "--seed", str(args.seed))
        rg("synth", str(work / "table"), "--objects", "7", "--views", str(args.table_views), "--seed", str(args.seed))
        rows.append(scene_rows("table top", work / "table", work, True))
        rows.append(scene_rows("synthetic room", work / "room", work, True))
        rows.append(scene_rows("synthetic room, close", work / "room_close", work, True))
        spacing = work / "spacing.yaml"
        spacing.write_text(f"map:\n  seed_spacing: {args.seed_spacing}\n")
        rows.append(scene_rows("synthetic room, seed spacing", work / "room", work, True, spacing))
        for seed in args.more_seeds:
            rg("synth", str(work / f"room_{seed}"), "--layout", "room", "--objects", str(args.objects), "--tables",
               str(args.tables), "--views", str(args.views), "--seed", str(seed))
            rg("synth", str(work / f"table_{seed}"), "--objects", "7", "--views", str(args.table_views), "--seed", str(seed))
            rows.append(scene_rows(f"table top, seed {seed}", work / f"table_{seed}", work, True))
            rows.append(scene_rows(f"synthetic room, seed {seed}", work / f"room_{seed}", work, True))
        if args.hires != "none":
            size, width = args.hires, args.hires.split("x")[0]
            for name, layout in (("room_hi", ("--layout", "room", "--objects", str(args.objects), "--tables",
                                             str(args.tables), "--views", str(args.views))),
                                 ("table_hi", ("--objects", "7", "--views", str(args.table_views)))):
                rg("synth", str(work / name), *layout, "--seed", str(args.seed), "--size", size)
            hires = work / "hires.yaml"
            hires.write_text(f"map:\n  width: {width}\n")
            rows.append(scene_rows(f"table top, {size}", work / "table_hi", work, True, hires))
            rows.append(scene_rows(f"synthetic room, {size}", work / "room_hi", work, True, hires))
        if Path(args.kitchen).is_dir():
            rows.append(scene_rows("redkitchen_100", Path(args.kitchen), work, False))
            rows.append(scene_rows("redkitchen_100, seed spacing", Path(args.kitchen), work, False, spacing))
    report = {"seed": args.seed, "objects": args.objects, "views": args.views, "tables": args.tables,
              "table_views": args.table_views, "close_radius": list(args.close_radius),
              "seed_spacing": args.seed_spacing, "more_seeds": args.more_seeds, "hires": args.hires,
              "synth_room_s": room["seconds"], "rows": rows}
    png = plot(report, Path(args.out) / "room.png")
    return finish(args, report, "bench_room", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
