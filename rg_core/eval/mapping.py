"""Map quality on held-out views: PSNR, depth error and coverage at the mapping resolution."""
from __future__ import annotations

import numpy as np
import torch

from ..io.scene import Frame
from ..map.frames import prepare_frame
from ..map.mapper import Mapper


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
    mean = lambda k: float(np.nanmean([r[k] for r in rows]))  # noqa: E731
    return {"views": len(rows), "psnr": round(mean("psnr"), 3), "psnr_valid_depth": round(mean("psnr_valid_depth"), 3),
            "depth_abs_error_median_m": round(float(np.nanmedian([r["depth_med"] for r in rows])), 5),
            "depth_abs_error_mean_m": round(mean("depth_mean"), 5), "coverage": round(mean("coverage"), 4),
            "coverage_valid_depth": round(mean("coverage_valid_depth"), 4)}
