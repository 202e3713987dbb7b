"""A camera as JSON, for masks and renders from any pose: {"K": 3x3, "cam_to_world": 4x4 (OpenCV
axes: x right, y down, z forward), "width", "height"} (rg ground --pose, examples/amodal_mask.py)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def read_camera_json(path: str | Path) -> tuple[np.ndarray, np.ndarray, int, int]:
    """-> (K [3, 3], cam_to_world [4, 4] float64, width, height); ValueError naming what is wrong."""
    try:
        d = json.loads(Path(path).read_text())
        K, c2w = np.asarray(d["K"], np.float64), np.asarray(d["cam_to_world"], np.float64)
        w, h = int(d["width"]), int(d["height"])
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: pose file needs K [3x3], cam_to_world [4x4], width, height ({exc})") from exc
    if K.shape != (3, 3) or c2w.shape != (4, 4) or not np.isfinite(K).all() or not np.isfinite(c2w).all():
        raise ValueError(f"{path}: K must be finite 3x3 and cam_to_world finite 4x4")
    if w <= 0 or h <= 0:
        raise ValueError(f"{path}: width and height must be positive, got {w}x{h}")
    return K, c2w, w, h
