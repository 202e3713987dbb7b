"""Scale normalisation of photo-only worlds: COLMAP, LLFF and nerfstudio poses are defined only up
to scale, while the mapper's, the supervision's and the grounder's defaults are in metres.

The rule (applied once, on read, by captures.read_scene; `photo.world_scale` and
`photo.world_depth` in the config):

- Scenes in metres keep their world: every scene with depth images (the depth fixes the unit) and
  every other layout (ReasoningGD, captures, BOP, YCB-Video, bags).
- A COLMAP, LLFF or nerfstudio scene without depth is multiplied by a factor s: poses' translations,
  sparse points and LLFF's near / far bounds (rotations and intrinsics do not change).
  `world_scale > 0` gives s; `0` (auto) derives it so that the scene's typical viewing distance D
  becomes `world_depth` metres (s = world_depth / D), D being, by the first rule that applies:
  1. "points": the median over the views of the median depth of the sparse points in front of the
     view and inside its image (views that see fewer than 10 points left out);
  2. "bounds": the median over the views of the geometric mean of LLFF's near and far bounds;
  3. "cameras": the median distance of the camera centres from their centroid (an orbit's radius;
     a poor guess for a forward-facing capture from one spot: give world_scale then);
  4. "none": s = 1 when none of these is positive (a single camera without points).
- The factor and the rule are recorded in the Scene (`world_scale`, `world_rule`) and, through
  map.run.build_map, in the map (`mapper.built`) and `rg map`'s report: lengths the map reports
  divided by `world_scale` are in the source's own units.
"""
from __future__ import annotations

import logging

import numpy as np

from ..geometry.conventions import in_image, project
from .scene import Scene

log = logging.getLogger(__name__)

UNSCALED_KINDS = ("colmap", "llff", "nerfstudio")   # layouts whose world is defined only up to scale
_MAX_POINTS = 20000   # points the "points" rule projects (an even stride through the cloud)
_MIN_SEEN = 10        # points a view must see to take part in it


def viewing_distance(scene: Scene) -> tuple[float, str]:
    """(D, rule): the scene's typical viewing distance in its own units and the rule that gave it
    (module docstring); D = 0 with rule "none" when no rule applies."""
    frames = scene.frames
    pts = scene.load_points()
    if pts is not None and len(pts.xyz):
        xyz = np.asarray(pts.xyz, np.float64)[:: max(1, len(pts.xyz) // _MAX_POINTS)]
        xyz = xyz[np.isfinite(xyz).all(1)]
        per_view = []
        for f in frames:
            uv, z = project(xyz, f.intrinsics.K, np.asarray(f.cam_to_world, np.float64))
            seen = in_image(uv, z, f.intrinsics.width, f.intrinsics.height)
            if seen.sum() >= _MIN_SEEN:
                per_view.append(float(np.median(z[seen])))
        if per_view:
            return float(np.median(per_view)), "points"
    bounds = [f.bounds for f in frames if f.bounds is not None and min(f.bounds) > 0]
    if bounds:
        return float(np.median([np.sqrt(a * b) for a, b in bounds])), "bounds"
    if len(frames) >= 2:
        c = np.stack([np.asarray(f.cam_to_world, np.float64)[:3, 3] for f in frames])
        spread = float(np.median(np.linalg.norm(c - c.mean(0), axis=1)))
        if spread > 1e-9 * max(1.0, float(np.abs(c).max())):
            return spread, "cameras"
    return 0.0, "none"


def normalise_scale(scene: Scene, world_scale: float, world_depth: float) -> Scene:
    """Apply the rule of the module docstring to `scene` in place (and return it): its frames' poses,
    bounds and sparse points multiplied by the factor, recorded in scene.world_scale / world_rule."""
    if world_scale < 0 or not np.isfinite(world_scale):
        raise ValueError(f"photo.world_scale must be 0 (auto) or a positive factor, got {world_scale}")
    if world_depth <= 0 or not np.isfinite(world_depth):
        raise ValueError(f"photo.world_depth must be positive metres, got {world_depth}")
    if scene.kind not in UNSCALED_KINDS or any(f.depth_path is not None for f in scene.frames):
        scene.world_scale, scene.world_rule = 1.0, "metric"
        return scene
    scene.load_points()   # a PLY beside the poses is read now, to be scaled with them
    if world_scale > 0:
        s, rule = float(world_scale), "given"
    else:
        d, rule = viewing_distance(scene)
        s = world_depth / d if d > 0 else 1.0
        if d <= 0:
            log.warning("%s: no sparse points, bounds or camera spread to derive the world's scale from; kept as "
                        "it is (give photo.world_scale)", scene.root)
    for f in scene.frames:
        f.cam_to_world = np.array(f.cam_to_world, np.float64)
        f.cam_to_world[:3, 3] *= s
        if f.bounds is not None:
            f.bounds = (f.bounds[0] * s, f.bounds[1] * s)
    if scene.points is not None:
        scene.points.xyz = np.asarray(scene.points.xyz, np.float64) * s
    scene.world_scale, scene.world_rule = s, rule
    log.info("%s: world scaled by %.6g (%s rule) to metres", scene.root, s, rule)
    return scene
