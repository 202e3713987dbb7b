"""Depth reprojection consistency between two posed views (a check on poses, K and depth units)."""
from __future__ import annotations

import warnings

import numpy as np

from .conventions import backproject, project


def reprojection_depth_errors(depth_a: np.ndarray, K_a: np.ndarray, c2w_a: np.ndarray,
                              depth_b: np.ndarray, K_b: np.ndarray, c2w_b: np.ndarray,
                              occlusion_margin: float = 0.05, edge_jump: float = 0.02) -> np.ndarray:
    """|z predicted - z measured| (m) for depth pixels of view A that land on surfaces of view B.

    Pixels are dropped where they cannot be compared: outside B, behind B's camera, invalid depth
    in B, at a depth discontinuity of B (3x3 range above `edge_jump`), or occluded in B (predicted
    depth more than `occlusion_margin` behind B's surface).
    """
    assert depth_a.ndim == 2 and depth_b.ndim == 2, (depth_a.shape, depth_b.shape)
    va = depth_a > 0
    pts = backproject(depth_a, K_a, c2w_a)[va]  # [N, 3]
    uv, z = project(pts, K_b, c2w_b)
    H, W = depth_b.shape
    u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    inside = (z > 0) & (u >= 1) & (v >= 1) & (u < W - 1) & (v < H - 1)
    u, v, z = u[inside].astype(int), v[inside].astype(int), z[inside]
    db = depth_b.astype(np.float64)
    pad = np.pad(np.where(db > 0, db, np.nan), 1, mode="edge")
    win = np.stack([pad[1 + dy: 1 + dy + H, 1 + dx: 1 + dx + W] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    with warnings.catch_warnings():  # windows of all-invalid depth give NaN, dropped below
        warnings.simplefilter("ignore", RuntimeWarning)
        jump = np.nanmax(win, 0) - np.nanmin(win, 0)
    zb = db[v, u]
    ok = (zb > 0) & np.isfinite(jump[v, u]) & (jump[v, u] <= edge_jump) & (z <= zb + occlusion_margin)
    return np.abs(z[ok] - zb[ok])
