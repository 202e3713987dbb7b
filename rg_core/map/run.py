"""Stream a scene's training frames through the Mapper (what `rg map` and the benchmarks run)."""
from __future__ import annotations

import sys
import time

from ..config import MapConfig
from ..eval.mapping import evaluate_views
from ..io.captures import read_scene
from ..util import peak_rss_mb
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


def map_scene(scene_dir, cfg: MapConfig, progress: bool = True, bag_options=None) -> tuple[Mapper, dict]:
    """Map the training frames of a scene (folder or ROS 2 bag) and evaluate on its test frames."""
    scene = read_scene(scene_dir, test_every=8, bag_options=bag_options)
    mapper = Mapper(cfg)
    seconds = stream_frames(mapper, scene.train, progress)
    seconds += mapper.refine(cfg.final_iters)
    t = time.perf_counter()
    quality = evaluate_views(mapper, scene.test)
    report = {**mapper.stats(), "seconds_total": round(seconds, 3), "seconds_eval": round(time.perf_counter() - t, 3),
              "test": quality, "peak_rss_mb": round(peak_rss_mb(), 1), "scene": str(scene_dir),
              "train_frames": len(scene.train), "test_frames": len(scene.test)}
    if getattr(scene, "info", None):   # a bag: topics used, frames dropped (TF missing, ...) per reason
        report["bag"] = scene.info
    return mapper, report
