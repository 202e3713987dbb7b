"""Map a scene folder and make it answerable: Gaussians from its posed RGB-D frames, 2D supervision
(masks + embeddings) per keyframe, the feature field trained; saved as one map file.

    python examples/map_scene.py SCENE OUT.rgmap [--supervision default|oracle] [--field-seconds S]

SCENE: a ReasoningGD folder (`rg synth` makes one), a capture folder, a BOP scene or a ROS 2 bag.
The same as `rg map SCENE --out OUT --supervise --train-field S`, through the Python API.
"""
import argparse
import dataclasses

from rg_core.config import load_config
from rg_core.grounding.build import build_grounder
from rg_core.io.captures import read_scene
from rg_core.map.store import save_map

ap = argparse.ArgumentParser()
ap.add_argument("scene")
ap.add_argument("out")
ap.add_argument("--supervision", default="default", help="default (the offline models) or oracle (ground truth)")
ap.add_argument("--field-seconds", type=float, default=30.0)
ap.add_argument("--width", type=int, default=0, help="mapping width in pixels (0: the configured 320)")
args = ap.parse_args()

cfg = load_config(None)
if args.width:
    cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, width=args.width))
scene = read_scene(args.scene)
grounder, report = build_grounder(scene, cfg, supervision=args.supervision, field_seconds=args.field_seconds)
path = save_map(grounder.mapper, args.out)
print(f"{path}: {len(grounder.mapper.keyframes)} keyframes, {len(grounder.mapper.gaussians)} Gaussians, "
      f"{grounder.field.steps} field steps")
