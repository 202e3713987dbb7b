"""Checking and preparing one incoming RGB-D frame before it may touch the map."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry.conventions import PoseError, check_rigid, scale_intrinsics


class FrameError(ValueError):
    """A frame that cannot be used; the map is left untouched."""


@dataclass
class PreparedFrame:
    """A frame at the mapper's working resolution."""

    rgb: np.ndarray          # [h, w, 3] float32 in [0, 1]
    depth: np.ndarray        # [h, w] float32 metres, 0 = invalid
    K: np.ndarray            # [3, 3] scaled to the working resolution
    cam_to_world: np.ndarray  # [4, 4] OpenCV axes
    stamp: float


def check_frame(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray, stamp: float,
                min_valid: float = 0.01) -> None:
    """Raise FrameError naming the problem, or return None if the frame can be mapped."""
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise FrameError(f"rgb must be an [H, W, 3] array, got {getattr(rgb, 'shape', type(rgb))}")
    if rgb.dtype != np.uint8:
        raise FrameError(f"rgb must be uint8, got {rgb.dtype}")
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise FrameError(f"depth must be an [H, W] array, got {getattr(depth, 'shape', type(depth))}")
    if depth.dtype not in (np.float32, np.float64):
        raise FrameError(f"depth must be float32/float64 metres (convert uint16 mm first), got {depth.dtype}")
    if depth.shape != rgb.shape[:2]:
        raise FrameError(f"depth is {depth.shape[1]}x{depth.shape[0]} but rgb is {rgb.shape[1]}x{rgb.shape[0]}")
    if min(depth.shape) < 8:
        raise FrameError(f"image of {depth.shape[1]}x{depth.shape[0]} is too small (at least 8x8)")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise FrameError(f"K must be a finite 3x3 matrix with positive focal lengths, got {K.tolist()}")
    try:
        check_rigid(cam_to_world, "cam_to_world")
    except PoseError as exc:
        raise FrameError(str(exc)) from exc
    if not np.isfinite(stamp):
        raise FrameError(f"stamp must be finite, got {stamp}")
    valid = np.isfinite(depth) & (depth > 0)
    if valid.mean() < min_valid:
        raise FrameError(f"only {100 * valid.mean():.2f}% of depth pixels are valid (need {100 * min_valid:.0f}%)")
    med = float(np.median(depth[valid]))
    if med > 50.0 or med < 0.01:
        raise FrameError(f"median depth {med:.4g} m is outside [0.01, 50] m: depth in the wrong unit?")


def downscale_depth(depth: np.ndarray, w: int, h: int, max_std: float = 0.02) -> np.ndarray:
    """Resize depth [H, W] (0 = invalid) to w x h: each output pixel is the mean of the valid input
    pixels it covers (sparse sensors: their holes fill in). Blocks whose valid depths spread by more
    than `max_std` (m) straddle an edge and become invalid instead of a flying pixel between surfaces."""
    valid = (depth > 0).astype(np.float32)
    d = depth.astype(np.float32) * valid
    n = cv2.resize(valid, (w, h), interpolation=cv2.INTER_AREA)
    s1 = cv2.resize(d, (w, h), interpolation=cv2.INTER_AREA)
    s2 = cv2.resize(d * d, (w, h), interpolation=cv2.INTER_AREA)
    ok = n > 1e-6
    mean = np.where(ok, s1 / np.maximum(n, 1e-6), 0.0)
    var = np.where(ok, s2 / np.maximum(n, 1e-6) - mean * mean, 0.0)
    return np.where(ok & (var <= max_std * max_std), mean, 0.0).astype(np.float32)


def map_camera(cfg, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int):
    """The rasterizer's Camera for a map's view: K and camera-to-world (numpy, OpenCV axes) with the
    map's clip planes (MapConfig near, far). What the Mapper and the photo fit both render with."""
    from ..render.camera import Camera

    return Camera.from_numpy(K, cam_to_world, width, height, cfg.near, cfg.far)


def working_size(W: int, H: int, width: int) -> tuple[int, int]:
    """(w, h) of an image W x H at the working width (never upsampled, aspect kept)."""
    w = min(width, W)
    return w, max(1, int(round(H * w / W)))


def prepare_frame(rgb, depth, K, cam_to_world, stamp, width: int) -> PreparedFrame:
    """Validate and resize to `width` pixels wide (aspect kept); depth with `downscale_depth`."""
    check_frame(rgb, depth, K, cam_to_world, stamp)
    H, W = depth.shape
    w, h = working_size(W, H, width)
    sx, sy = w / W, h / H
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    if (w, h) != (W, H):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        depth = downscale_depth(depth, w, h)
    return PreparedFrame(rgb.astype(np.float32) / 255.0, depth, scale_intrinsics(K, sx, sy), np.asarray(cam_to_world, np.float64), float(stamp))
