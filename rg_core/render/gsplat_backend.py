"""gsplat's CUDA `rasterization` as a backend for CUDA tensors (optional; never required).

gsplat puts pixel centres at +0.5, so the principal point is shifted by half a pixel on the way
in. It reports no per-pixel Gaussian id: `ids` is None with this backend.
"""
from __future__ import annotations

import torch

from .camera import Camera
from .types import RenderOutput


def rasterize_gsplat(means, scales, quats, opacities, channels, camera: Camera, background, eps2d: float,
                     antialiased: bool = False):
    try:
        from gsplat import rasterization
    except ImportError as exc:
        raise RuntimeError("backend 'gsplat' needs the gsplat package (pip install gsplat) and CUDA") from exc

    dev = means.device
    K = camera.K.to(dev, torch.float32).clone()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    bg = None
    if background is not None:
        bg = torch.cat([background.to(dev, torch.float32), background.new_zeros(1).to(dev)])[None]
    colors, alphas, _meta = rasterization(
        means.float(), quats.float(), scales.float().abs(), opacities.float().clamp(0, 1), channels.float(),
        camera.world_to_cam.to(dev, torch.float32)[None], K[None], camera.width, camera.height,
        near_plane=camera.near, far_plane=camera.far, eps2d=eps2d, render_mode="RGB+ED",
        backgrounds=bg, rasterize_mode="antialiased" if antialiased else "classic")
    C = channels.shape[1]
    return RenderOutput(colors[0, ..., :C], colors[0, ..., C], alphas[0, ..., 0], None, None)
