"""The photo fit's image losses (photo_fit.py): SSIM for 3DGS's D-SSIM term, and the edge-aware
smoothness of a rendered depth for captures with little parallax."""
from __future__ import annotations

import torch


def depth_smoothness(depth: torch.Tensor, alpha: torch.Tensor, rgb: torch.Tensor, edge: float = 10.0) -> torch.Tensor:
    """Edge-aware smoothness of a rendered depth [H, W] (expected depth, alpha [H, W]) against the
    photo it should follow (rgb [H, W, 3] in [0, 1]): the mean over neighbouring pixels, both
    covered, of |depth step| x exp(-edge x |colour step|), relative to the median depth. Depth may
    jump where the colour does; elsewhere photos with little parallax say nothing about it, and
    this keeps their surfaces whole instead of scattered along the rays."""
    opaque = alpha > 0.5
    scale = depth[opaque].median().detach() if bool(opaque.any()) else depth.new_tensor(1.0)
    total = depth.new_zeros(())
    for d in (1, 0):   # horizontal, then vertical neighbours
        n = depth.shape[d] - 1
        w = torch.exp(-edge * torch.diff(rgb, dim=d).abs().mean(-1)) * (opaque.narrow(d, 1, n) & opaque.narrow(d, 0, n))
        total = total + (torch.diff(depth, dim=d).abs() * w).sum() / w.sum().clamp(min=1.0)
    return total / scale.clamp(min=1e-6)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SSIM of two images [H, W, 3] in [0, 1] (pytorch_msssim, 11 px Gaussian window, sigma 1.5)."""
    from pytorch_msssim import ssim as _ssim

    return _ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], data_range=1.0, size_average=True,
                 win_size=11 if min(a.shape[:2]) >= 11 else (min(a.shape[:2]) // 2) * 2 - 1)
