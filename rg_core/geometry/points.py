"""Point-set measures shared by the layers above (the map's resolution)."""
from __future__ import annotations

import numpy as np


def map_spacing(points: np.ndarray, sample: int = 4000, seed: int = 0) -> float:
    """Median nearest-neighbour distance (m) of points [N, 3] (a sample of them): the map's resolution."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    if len(pts) < 2:
        return 0.0
    sub = pts if len(pts) <= sample else pts[np.random.default_rng(seed).choice(len(pts), sample, replace=False)]
    d, _ = cKDTree(pts).query(sub, k=2)
    return float(np.median(d[:, 1]))
