"""`rg map` on a ROS 2 bag against `rg map` on the scene folder it was written from (issue 16).

Writes the capture folder as a RealSense-style mcap bag (JPEG colour, compressedDepth PNG depth,
CameraInfo, TF map -> odom -> base_link + static base_link -> camera_link -> optical frame), maps
both with the same configuration and prints the test PSNR of each, the difference, the pose error
of the TF lookups and the bag size. The target: |PSNR(bag) - PSNR(folder)| <= 0.2 dB.

  python benchmarks/bench_bag.py [--scene ../shared/data/rgbd/box_toys_50] [--frames 0] [--width 320] [--record]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rg_core.config import load_config
from rg_core.io.captures import read_scene
from rg_core.io.rosbag import read_bag
from rg_core.io.rosbag_write import write_scene_bag
from rg_core.eval.mapping import map_scene

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_output_flags, finish  # noqa: E402


def to_rows(out: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: the folder and the bag mapped with the same configuration."""
    rows = [{"source": k, "psnr_db": round(out[k]["psnr"], 2), "gaussians": out[k]["gaussians"],
             "keyframes": out[k]["keyframes"], "time_s": round(out[k]["seconds"], 1)} for k in ("folder", "bag")]
    rows[1]["psnr_diff_db"] = out["psnr_diff_db"]
    return rows, (f"{Path(out['scene']).name}, {out['frames']} frames mapped at width {out['width']}, "
                  f"{out['iters_per_keyframe']} it/kf + {out['final_iters']} final; bag {out['bag_mb']} MB "
                  f"(JPEG {out['jpeg_quality']}), TF pose error max {out['tf_pose_max_abs_error']:.1e}; "
                  "target |PSNR diff| <= 0.2 dB")


def subset_folder(src: Path, n: int, dst: Path) -> Path:
    """The first n frames of a capture folder as symlinks (n = 0: the folder itself)."""
    if n <= 0:
        return src
    dst.mkdir(parents=True, exist_ok=True)
    for p in sorted(src.glob("*.K.txt")) + sorted(src.glob("camera-intrinsics.txt")):
        os.symlink(p.resolve(), dst / p.name)
    fids = sorted(p.name.split(".")[0] for p in src.glob("frame-*.color.*"))[:n]
    for fid in fids:
        for p in src.glob(f"{fid}.*"):
            os.symlink(p.resolve(), dst / p.name)
    return dst


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=str(ROOT.parent / "shared/data/rgbd/box_toys_50"))
    ap.add_argument("--frames", type=int, default=0, help="first N frames (0 = all)")
    ap.add_argument("--width", type=int, default=0, help="mapping width (0 = config)")
    ap.add_argument("--iters", type=int, default=0, help="iterations per keyframe (0 = config)")
    ap.add_argument("--final-iters", type=int, default=-1, help="final refinement iterations (-1 = config)")
    ap.add_argument("--jpeg-quality", type=int, default=95)
    ap.add_argument("--out", default="", help="also write the JSON here")
    add_output_flags(ap, json_flag=False)
    args = ap.parse_args()
    cfg = load_config(None).map
    over = {k: v for k, v in (("width", args.width), ("iters_per_keyframe", args.iters)) if v > 0}
    if args.final_iters >= 0:
        over["final_iters"] = args.final_iters
    cfg = dataclasses.replace(cfg, **over)
    tmp = Path(tempfile.mkdtemp(prefix="rg_bench_bag_"))
    try:
        folder = subset_folder(Path(args.scene), args.frames, tmp / "scene")
        frames = read_scene(folder, test_every=0).train
        t = time.perf_counter()
        # the folder's frames are stamped by index (1 s apart); keyframe selection reads stamps
        # (map.kf_min_interval), so the bag keeps that timing
        bag = write_scene_bag(frames, tmp / "bag", jpeg_quality=args.jpeg_quality, period=1.0)
        t_write = time.perf_counter() - t
        size = sum(p.stat().st_size for p in bag.iterdir())
        t = time.perf_counter()
        scene_bag = read_bag(bag, test_every=0)
        t_read = time.perf_counter() - t
        pose_err = max(float(np.abs(a.cam_to_world - b.cam_to_world).max()) for a, b in zip(scene_bag.train, frames))
        runs = {}
        for name, src in (("folder", folder), ("bag", bag)):
            torch_seed()
            _, rep = map_scene(src, cfg, progress=False)
            runs[name] = {"psnr": rep["test"]["psnr"], "gaussians": rep["gaussians"], "keyframes": rep["keyframes"],
                          "seconds": rep["seconds_total"], "train_frames": rep["train_frames"],
                          "test_frames": rep["test_frames"]}
            print(f"{name}: {runs[name]}", file=sys.stderr)
        out = {"scene": str(args.scene), "frames": len(frames), "width": cfg.width,
               "iters_per_keyframe": cfg.iters_per_keyframe, "final_iters": cfg.final_iters,
               "jpeg_quality": args.jpeg_quality, "bag_mb": round(size / 1e6, 2), "write_s": round(t_write, 2),
               "read_s": round(t_read, 3), "tf_pose_max_abs_error": pose_err, **runs,
               "psnr_diff_db": round(runs["bag"]["psnr"] - runs["folder"]["psnr"], 3),
               "gaussians_ratio": round(runs["bag"]["gaussians"] / max(runs["folder"]["gaussians"], 1), 4)}
        print(json.dumps(out))
        print("| source | test PSNR (dB) | Gaussians | keyframes | s |\n|---|---|---|---|---|\n"
              + "\n".join(f"| {k} | {runs[k]['psnr']:.2f} | {runs[k]['gaussians']} | {runs[k]['keyframes']} | "
                          f"{runs[k]['seconds']:.0f} |" for k in runs), file=sys.stderr)
        if args.out:
            Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
        finish(args, out, "bench_bag", to_rows)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def torch_seed() -> None:
    import torch

    torch.manual_seed(0)
    np.random.seed(0)


if __name__ == "__main__":
    sys.exit(main())
