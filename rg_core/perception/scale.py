"""Physical scale of a 2D mask: the robust spread of its back-projected 3D points (metres)."""
from __future__ import annotations

import numpy as np


class MaskScaleError(ValueError):
    """A mask whose scale cannot be measured (too few valid depth pixels, wrong shape)."""


def mask_scale(mask: np.ndarray, depth: np.ndarray, K: np.ndarray, rendered_depth: np.ndarray | None = None,
               min_points: int = 20) -> float:
    """Scale s of a mask, as in the paper: the standard deviation of the mask's 3D points.

    mask [H, W] bool, depth [H, W] metres (0/NaN invalid). Sensor depth is used where valid and
    `rendered_depth` (from the map) fills the rest. s = sqrt(trace of the covariance) of the points
    (their RMS distance to the centroid), computed on inliers only: points further than 3 robust
    standard deviations (1.4826 x MAD) from the median on any axis, such as flying pixels at object
    edges, are left out. For compact shapes nothing is left out and s is exact.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2 or mask.shape != depth.shape:
        raise MaskScaleError(f"mask {mask.shape} and depth {depth.shape} must be [H, W] of the same size")
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    if rendered_depth is not None:
        if rendered_depth.shape != depth.shape:
            raise MaskScaleError(f"rendered depth {rendered_depth.shape} must match depth {depth.shape}")
        r = np.where(np.isfinite(rendered_depth) & (rendered_depth > 0), rendered_depth, 0.0)
        d = np.where(d > 0, d, r)
    vs, us = np.nonzero(mask & (d > 0))
    if len(vs) < min_points:
        raise MaskScaleError(f"mask has {len(vs)} pixels with valid depth, need at least {min_points}")
    z = d[vs, us].astype(np.float64)
    pts = np.stack([(us - K[0, 2]) * z / K[0, 0], (vs - K[1, 2]) * z / K[1, 1], z], 1)
    med = np.median(pts, 0)
    robust_std = np.median(np.abs(pts - med), 0) * 1.4826
    inl = np.all(np.abs(pts - med) <= 3.0 * robust_std + 1e-9, axis=1)
    if inl.sum() < min_points:
        inl = np.ones(len(pts), bool)  # degenerate spread (e.g. a flat patch): keep all
    return float(np.sqrt(pts[inl].var(0).sum()))
