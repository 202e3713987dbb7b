"""What a render returns (shared by rasterize() and its backends)."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .projection import Projected


@dataclass
class RenderOutput:
    """Per-pixel results. `depth` is the expected depth (alpha-normalised); 0 where alpha ~ 0."""

    channels: torch.Tensor        # [H, W, C]
    depth: torch.Tensor           # [H, W]
    alpha: torch.Tensor           # [H, W] accumulated opacity in [0, 1]
    ids: torch.Tensor | None      # [H, W] int64, Gaussian with the largest blending weight, -1 none
    projected: Projected | None   # screen-space Gaussians (None for the gsplat backend)
