"""Pinhole camera for the rasterizer (OpenCV axes and pixel-centre coordinates)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class Camera:
    """K [3, 3], world_to_cam [4, 4] (OpenCV axes), image size and clip planes (m)."""

    K: torch.Tensor
    world_to_cam: torch.Tensor
    width: int
    height: int
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self):
        assert tuple(self.K.shape) == (3, 3), f"K must be [3, 3], got {tuple(self.K.shape)}"
        assert tuple(self.world_to_cam.shape) == (4, 4), f"world_to_cam must be [4, 4], got {tuple(self.world_to_cam.shape)}"
        if self.width < 1 or self.height < 1:
            raise ValueError(f"Camera: image size must be at least 1x1, got {self.width}x{self.height}")
        if not (0.0 < self.near < self.far) or not np.isfinite(self.far):
            raise ValueError(f"Camera: need 0 < near < far < inf, got near={self.near}, far={self.far}")
        if not bool(torch.isfinite(self.K).all()) or float(self.K[0, 0]) <= 0 or float(self.K[1, 1]) <= 0:
            raise ValueError(f"Camera: K must be finite with positive focal lengths, got {self.K.tolist()}")
        if not bool(torch.isfinite(self.world_to_cam).all()):
            raise ValueError("Camera: world_to_cam contains NaN or inf")

    @staticmethod
    def from_numpy(K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
                   near: float = 0.01, far: float = 100.0) -> "Camera":
        """From numpy K and a camera-to-world pose (the library's pose convention)."""
        w2c = np.linalg.inv(np.asarray(cam_to_world, dtype=np.float64))
        return Camera(torch.as_tensor(np.asarray(K), dtype=torch.float32),
                      torch.as_tensor(w2c, dtype=torch.float32), int(width), int(height), near, far)
