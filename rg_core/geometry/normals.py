"""Surface normals of organised point clouds (a depth image back-projected): the mask generator's
creases (perception.masks.rgbd) and the concave seams that split a point answer (grounding.parts)."""
from __future__ import annotations

import numpy as np

from .conventions import pixels_to_points


def organised_normals(pts: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unit normals [H, W, 3] of an organised cloud pts [H, W, 3] (valid [H, W] bool): the cross
    product of its central differences (x right by y down: away from the camera for a surface
    facing it); 0 where the pixel is not valid or the differences are degenerate."""
    dx, dy = np.zeros_like(pts), np.zeros_like(pts)
    dx[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    dy[1:-1] = pts[2:] - pts[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), 0.0)
    n[~valid] = 0.0
    return n


def depth_normals(depth: np.ndarray, K: np.ndarray, step: int = 1, median_px: int = 0,
                  pixels: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Depth image [H, W] (m, 0 / NaN / inf = unknown), intrinsics K [3, 3] -> unit normals in the
    camera frame, turned towards the camera: [H, W, 3], or [n, 3] at `pixels` (rows [n], cols [n]:
    a few pixels cost a few, not an image). From the depths `step` px left, right, up and down,
    each the median of the known depths in its median_px x median_px window (0: the reading;
    a sensor's speckle turns normals more than its noise moves points). 0 where the pixel has no
    reading, or one of those four has no depth or a window leaving the image."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth_normals: depth must be [H, W], got {list(d.shape)}")
    if median_px < 0 or (median_px and median_px % 2 == 0):
        raise ValueError(f"depth_normals: median_px must be 0 or odd, got {median_px}")
    H, W = d.shape

    def read(R, C):   # depth [...] at pixels R, C (clipped onto the image), NaN where unknown
        z = d[np.clip(R, 0, H - 1), np.clip(C, 0, W - 1)].astype(np.float64)
        return np.where(np.isfinite(z) & (z > 0), z, np.nan)

    if pixels is None:
        rows, cols = (a.reshape(-1) for a in np.meshgrid(np.arange(H), np.arange(W), indexing="ij"))
    else:
        rows, cols = (np.asarray(a, np.int64).reshape(-1) for a in pixels)
    s, r = max(1, int(step)), median_px // 2
    off = np.arange(-r, r + 1)
    wr, wc = (o.reshape(-1) for o in np.meshgrid(off, off, indexing="ij"))            # [w] window offsets

    def at(rr, cc):   # median-filtered depth [n] at pixels rr, cc [n]; NaN where it has none
        R, C = rr[:, None] + wr, cc[:, None] + wc                                    # [n, w]
        inside = ((R >= 0) & (R < H) & (C >= 0) & (C < W)).all(1)
        win = np.sort(read(R, C), axis=1)                                             # NaN last
        k = np.isfinite(win).sum(1)                                                    # [n] readings
        lo, hi = (np.take_along_axis(win, np.maximum(x, 0)[:, None], 1)[:, 0] for x in ((k - 1) // 2, k // 2))
        return np.where(inside & (k > 0), 0.5 * (lo + hi), np.nan)

    K = np.asarray(K, np.float64)
    pt = [pixels_to_points(cc, rr, at(rr, cc), K) for rr, cc in
          ((rows, cols + s), (rows, cols - s), (rows + s, cols), (rows - s, cols))]   # 4 x [n, 3]
    centre = pixels_to_points(cols, rows, np.where(np.isfinite(read(rows, cols)), 1.0, np.nan), K)   # [n, 3] z = 1
    with np.errstate(all="ignore"):
        n = np.cross(pt[0] - pt[1], pt[2] - pt[3])                                     # x right by y down
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        ok = np.isfinite(norm[:, 0]) & (norm[:, 0] > 1e-300) & np.isfinite(centre).all(1)
        n = np.where(ok[:, None], n / np.where(ok[:, None], norm, 1.0), 0.0)
    n[(n * np.nan_to_num(centre)).sum(1) > 0] *= -1.0                                  # facing away: turn it
    n[~ok] = 0.0
    return n.reshape(H, W, 3) if pixels is None else n
