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
    scale = depth[alpha > 0.5].median().detach() if bool((alpha > 0.5).any()) else depth.new_tensor(1.0)
    terms = []
    for a, b, ia, ib, pa, pb in ((depth[:, 1:], depth[:, :-1], rgb[:, 1:], rgb[:, :-1], alpha[:, 1:], alpha[:, :-1]),
                                 (depth[1:], depth[:-1], rgb[1:], rgb[:-1], alpha[1:], alpha[:-1])):
        w = torch.exp(-edge * (ia - ib).abs().mean(-1)) * ((pa > 0.5) & (pb > 0.5))
        terms.append(((a - b).abs() * w).sum() / w.sum().clamp(min=1.0))
    return (terms[0] + terms[1]) / scale.clamp(min=1e-6)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SSIM of two images [H, W, 3] in [0, 1] (pytorch_msssim, 11 px Gaussian window, sigma 1.5)."""
    from pytorch_msssim import ssim as _ssim

    return _ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], data_range=1.0, size_average=True,
                 win_size=11 if min(a.shape[:2]) >= 11 else (min(a.shape[:2]) // 2) * 2 - 1)
