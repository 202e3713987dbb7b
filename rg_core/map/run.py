"""Stream frames through the Mapper (what `rg map`, the benchmarks and the tests run)."""
from __future__ import annotations

import sys
import time

from .mapper import Mapper


def stream_frames(mapper: Mapper, frames, progress: bool = True, desc: str = "map") -> float:
    """Feed frames in order; returns seconds."""
    from tqdm import tqdm

    t = time.perf_counter()
    bar = tqdm(frames, desc=desc, unit="frame", disable=not progress, file=sys.stderr)
    for f in bar:
        mapper.add_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, f.stamp)
        bar.set_postfix(kf=len(mapper.keyframes), g=len(mapper.gaussians))
    return time.perf_counter() - t


def build_map(scene, map_cfg, photo_cfg=None, progress: bool = True) -> tuple[Mapper, dict]:
    """A scene's training frames as a map, and how it was made: RGB-D frames streamed then refined
    (final_iters), or, when no training frame has a depth image, the photo-only fit
    (photo_fit.py: standard 3DGS from the sparse points, then rendered depth). A scene where only
    some frames have depth is refused (SceneError from require_depth). The record (kind, seconds,
    the world's scale and its rule: io/world_scale.py; the photo fit's summary) is also kept in the
    map (`mapper.built`, saved with it)."""
    t = time.perf_counter()
    world = {"world_scale": float(getattr(scene, "world_scale", 1.0)), "world_rule": getattr(scene, "world_rule", "metric")}
    if scene.has_depth() or any(f.depth_path is not None for f in scene.train):
        scene.require_depth()
        mapper = Mapper(map_cfg)
        stream_frames(mapper, scene.train, progress)
        mapper.refine(map_cfg.final_iters)
        built = {"kind": "rgbd", "seconds": round(time.perf_counter() - t, 3), **world}
    else:
        from .photo_fit import fit_summary, photo_mapper

        mapper, fit = photo_mapper(scene.train, map_cfg, photo_cfg, scene.load_points(), progress)
        built = {"kind": "photo", "seconds": round(time.perf_counter() - t, 3), **world, "photo": fit_summary(fit)}
    mapper.built = built
    return mapper, built
