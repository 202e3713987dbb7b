"""PNG reading and writing for colour, depth and masks, with errors that name the file."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


class SceneError(ValueError):
    """A scene on disk is missing a file or holds something of the wrong shape or unit."""


def _imread(path: Path, flags: int) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise SceneError(f"{path}: not a readable image")
    return img


def read_rgb(path: Path) -> np.ndarray:
    """-> uint8 [H, W, 3] RGB."""
    img = _imread(path, cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    assert rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.dtype == np.uint8, rgb.shape
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def read_depth(path: Path, depth_scale: float = 1000.0) -> np.ndarray:
    """16-bit depth PNG -> float32 [H, W] metres, 0 where invalid. `depth_scale` units per metre."""
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise SceneError(f"{path}: depth must be a single-channel uint16 PNG, got {raw.dtype} {raw.shape}")
    return raw.astype(np.float32) / np.float32(depth_scale)


def write_depth(path: Path, depth_m: np.ndarray, depth_scale: float = 1000.0) -> None:
    """float [H, W] metres -> uint16 PNG (0 = invalid; NaN/inf/negative/out of range -> 0)."""
    d = np.asarray(depth_m, dtype=np.float64) * depth_scale
    bad = ~np.isfinite(d) | (d <= 0) | (d > 65535)
    d = np.where(bad, 0, np.rint(d)).astype(np.uint16)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), d)


def read_mask(path: Path) -> np.ndarray:
    """uint8 [H, W] label or binary mask."""
    m = _imread(path, cv2.IMREAD_UNCHANGED)
    if m.ndim != 2 or m.dtype != np.uint8:
        raise SceneError(f"{path}: mask must be a single-channel uint8 PNG, got {m.dtype} {m.shape}")
    return m


def write_mask(path: Path, mask: np.ndarray) -> None:
    m = np.asarray(mask)
    if m.dtype == bool:
        m = m.astype(np.uint8) * 255
    assert m.ndim == 2 and m.dtype == np.uint8, (m.dtype, m.shape)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), m)


def check_depth_unit(depth_m: np.ndarray, where: str) -> None:
    """Flag depth in the wrong unit: median valid depth above 50 m or below 1 cm, or none valid."""
    valid = depth_m[np.isfinite(depth_m) & (depth_m > 0)]
    if valid.size == 0:
        raise SceneError(f"{where}: depth has no valid pixel")
    med = float(np.median(valid))
    if med > 50.0 or med < 0.01:
        raise SceneError(
            f"{where}: median depth {med:.4g} m is outside [0.01, 50] m; wrong depth unit or depth_scale?"
        )
