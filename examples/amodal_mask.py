"""Amodal and visible masks of a grounded object for any camera: the whole object (hidden parts
too) and the part the camera sees, written as PNGs.

    python examples/amodal_mask.py MAP.rgmap "query" OUT_DIR [--pose POSE.json]

POSE.json: {"K": 3x3, "cam_to_world": 4x4 (OpenCV axes: x right, y down, z forward), "width", "height"};
without it the camera of the answer's reference keyframe.
"""
import argparse
from pathlib import Path

import cv2
import numpy as np

from rg_core.config import load_config
from rg_core.grounding.pipeline import Grounder
from rg_core.io.camera_json import read_camera_json
from rg_core.map.store import load_map

ap = argparse.ArgumentParser()
ap.add_argument("map")
ap.add_argument("query")
ap.add_argument("out")
ap.add_argument("--pose", help="camera JSON (K, cam_to_world, width, height)")
args = ap.parse_args()

grounder = Grounder.from_map(load_map(args.map), load_config(None), source=args.map)
result = grounder.ground(args.query)
if not result.success:
    raise SystemExit(f"not grounded: {result.message}")
if args.pose:
    K, c2w, w, h = read_camera_json(args.pose)
else:
    kf = next(k for k in grounder.mapper.keyframes if k.index == result.reference_view)
    (w, h), K, c2w = kf.size, np.asarray(kf.K), np.asarray(kf.cam_to_world)
amodal, visible = grounder.masks(result, K, c2w, w, h)   # two bool [h, w]
out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)
for name, mask in (("amodal", amodal), ("visible", visible)):
    cv2.imwrite(str(out / f"{name}.png"), mask.astype(np.uint8) * 255)
print(f"{out}: amodal {int(amodal.sum())} px, visible {int(visible.sum())} px of {w}x{h}")
