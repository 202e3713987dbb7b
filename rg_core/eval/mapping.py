"""Map quality on held-out views (PSNR, depth error and coverage at the mapping resolution), and
`map_scene`: a scene mapped and evaluated, what `rg map` and the benchmarks report."""
from __future__ import annotations

import time

import numpy as np
import torch

from ..config import MapConfig, PhotoMapConfig
from ..io.captures import read_scene
from ..io.scene import Frame
from ..map.frames import prepare_frame
from ..map.mapper import Mapper
from ..map.run import build_map
from ..util import peak_rss_mb


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of images in [0, 1] over `mask` pixels (all if None)."""
    err = ((np.clip(pred, 0.0, 1.0) - gt) ** 2).mean(-1)
    mse = float(err[mask].mean()) if mask is not None else float(err.mean())
    return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))


def evaluate_views(mapper: Mapper, frames: list[Frame]) -> dict:
    """Render each frame's pose at the working resolution and compare with its RGB-D.

    - psnr: over the whole image (pixels the map cannot hold render the map's background),
    - psnr_valid_depth: over pixels with valid sensor depth (what a depth-seeded map can represent),
    - depth_abs_error_median/mean (m): where sensor depth is valid and alpha > 0.5,
    - coverage: fraction of pixels with accumulated alpha > 0.5 (and of valid-depth pixels).
    """
    rows = []
    for f in frames:
        if f.depth_path is None:   # a photo-only scene: colour only
            from ..map.photo_fit import photo_view

            v = photo_view(f, mapper.cfg.width)
            h, w = v.rgb.shape[:2]
            with torch.no_grad():
                out = mapper.render(v.K, v.cam_to_world, w, h, background=True)
            nan = float("nan")
            rows.append({"psnr": psnr(out.channels.numpy(), v.rgb.numpy()), "psnr_valid_depth": nan, "depth_med": nan,
                         "depth_mean": nan, "coverage": float((out.alpha.numpy() > 0.5).mean()),
                         "coverage_valid_depth": nan})
            continue
        fr = prepare_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, f.stamp, mapper.cfg.width)
        h, w = fr.depth.shape
        with torch.no_grad():
            out = mapper.render(fr.K, fr.cam_to_world, w, h, background=True)
        rgb, alpha, depth = out.channels.numpy(), out.alpha.numpy(), out.depth.numpy()
        valid = fr.depth > 0
        sel = valid & (alpha > 0.5)
        err = np.abs(depth[sel] - fr.depth[sel])
        rows.append({"psnr": psnr(rgb, fr.rgb), "psnr_valid_depth": psnr(rgb, fr.rgb, valid),
                     "depth_med": float(np.median(err)) if err.size else float("nan"),
                     "depth_mean": float(err.mean()) if err.size else float("nan"),
                     "coverage": float((alpha > 0.5).mean()), "coverage_valid_depth": float(sel.sum() / max(valid.sum(), 1))})
    if not rows:
        return {"views": 0}

    def mean(k, f=np.nanmean):   # NaN where no view has the figure (no depth: a photo-only scene)
        vals = np.array([r[k] for r in rows], float)
        return float(f(vals)) if np.isfinite(vals).any() else float("nan")

    return {"views": len(rows), "psnr": round(mean("psnr"), 3), "psnr_valid_depth": round(mean("psnr_valid_depth"), 3),
            "depth_abs_error_median_m": round(mean("depth_med", np.nanmedian), 5),
            "depth_abs_error_mean_m": round(mean("depth_mean"), 5), "coverage": round(mean("coverage"), 4),
            "coverage_valid_depth": round(mean("coverage_valid_depth"), 4)}


def map_scene(scene_dir, cfg: MapConfig, progress: bool = True, bag_options=None,
              photo: PhotoMapConfig | None = None) -> tuple[Mapper, dict]:
    """Map the training frames of a scene (folder or ROS 2 bag; without depth images: the
    photo-only fit, `photo`) and evaluate on its test frames."""
    scene = read_scene(scene_dir, test_every=8, bag_options=bag_options, photo=photo)
    mapper, built = build_map(scene, cfg, photo, progress)
    seconds = built["seconds"]
    t = time.perf_counter()
    quality = evaluate_views(mapper, scene.test)
    report = {**mapper.stats(), "seconds_total": round(seconds, 3), "seconds_eval": round(time.perf_counter() - t, 3),
              "test": quality, "peak_rss_mb": round(peak_rss_mb(), 1), "scene": str(scene_dir),
              "train_frames": len(scene.train), "test_frames": len(scene.test), "built": built}
    if getattr(scene, "info", None):   # a bag: topics used, frames dropped (TF missing, ...) per reason
        report["bag"] = scene.info
    return mapper, report
