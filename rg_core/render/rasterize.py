"""`rasterize()`: the one public rendering function (3DGS equations) with three backends.

- "reference": pure torch, tile by tile, autograd (slow; the ground truth in tests),
- "cpu": the C++/OpenMP kernel with its own backward pass (default on CPU),
- "gsplat": gsplat's CUDA `rasterization` for CUDA tensors (optional dependency).
"""
from __future__ import annotations

import logging
import torch

from . import fast_cpu
from .camera import Camera
from .projection import EPS2D, Projected, project_gaussians
from .reference import rasterize_reference
from .types import RenderOutput

log = logging.getLogger(__name__)

BACKENDS = ("auto", "cpu", "reference", "gsplat")


def _select(subset: torch.Tensor | None, n: int) -> torch.Tensor | None:
    """Boolean mask [N] or index list -> sorted unique int64 indices (None: all)."""
    if subset is None:
        return None
    subset = torch.as_tensor(subset)
    if subset.dtype == torch.bool:
        if subset.shape != (n,):
            raise ValueError(f"rasterize: boolean subset must have shape [{n}], got {list(subset.shape)}")
        return torch.nonzero(subset).squeeze(1)
    idx = subset.reshape(-1).long()
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= n):
        raise ValueError(f"rasterize: subset indices must lie in [0, {n}), got [{int(idx.min())}, {int(idx.max())}]")
    return torch.unique(idx)


def rasterize(means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor, opacities: torch.Tensor,
              channels: torch.Tensor, camera: Camera, *, subset: torch.Tensor | None = None,
              background: torch.Tensor | None = None, return_ids: bool = False, backend: str = "auto",
              tile: int = 16, eps2d: float = EPS2D, antialiased: bool = False) -> RenderOutput:
    """Render Gaussians into `camera` with front-to-back alpha compositing.

    means [N, 3] (world, m), scales [N, 3] (std devs, m), quats [N, 4] (w, x, y, z; any norm),
    opacities [N] in [0, 1], channels [N, C] (any features: RGB, latent, instance ...). `subset`
    (bool [N] or indices) renders only those Gaussians; `ids` then still index the full set.
    `antialiased` scales each opacity so that the eps2d dilation keeps the Gaussian's integral
    (`antialias`; gsplat's "antialiased" mode), else its peak (3DGS's classic filter).
    Gradients flow to means, scales, quats, opacities and channels.
    """
    N = means.shape[0]
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterize: means must be [N, 3], got {list(means.shape)}")
    for name, t, shape in (("scales", scales, (N, 3)), ("quats", quats, (N, 4)), ("opacities", opacities, (N,))):
        if tuple(t.shape) != shape:
            raise ValueError(f"rasterize: {name} must be {list(shape)}, got {list(t.shape)}")
    if channels.ndim != 2 or channels.shape[0] != N:
        raise ValueError(f"rasterize: channels must be [N={N}, C], got {list(channels.shape)}")
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")
    C = channels.shape[1]
    if background is not None and tuple(background.shape) != (C,):
        raise ValueError(f"rasterize: background must be [{C}], got {list(background.shape)}")

    idx = _select(subset, N)
    if idx is not None:
        means, scales, quats, opacities, channels = (t[idx] for t in (means, scales, quats, opacities, channels))

    if backend == "auto":
        backend = "gsplat" if means.is_cuda else ("cpu" if fast_cpu.available() else "reference")
        if backend == "reference":
            log.warning("fast CPU rasterizer not built; using the slow pure-torch reference")
    if backend == "gsplat":
        from .gsplat_backend import rasterize_gsplat

        out = rasterize_gsplat(means, scales, quats, opacities, channels, camera, background, eps2d, antialiased)
        if idx is not None and out.ids is not None:
            out.ids = torch.where(out.ids >= 0, idx.to(out.ids.device)[out.ids.clamp(min=0)], out.ids)
        return out

    if backend == "cpu":
        proj = fast_cpu.project_fast(means, scales, quats, opacities, camera, eps2d)
    else:
        proj = project_gaussians(means, scales, quats, opacities, camera, eps2d)
    if antialiased:
        proj = antialias(proj, eps2d)
    W, H = camera.width, camera.height
    # Depth is composited as one more channel, then normalised by alpha: the expected depth.
    ch = torch.cat([channels.float(), proj.depths[:, None]], 1)
    if backend == "cpu":
        out, alpha, ids = fast_cpu.rasterize_fast(proj, ch, W, H, tile)
    else:
        out, alpha, ids = rasterize_reference(proj, ch, W, H, tile, return_ids=return_ids)
    color, depth_sum = out[..., :C], out[..., C]
    # Where almost nothing was hit, the normalised depth is meaningless (and 0/0): report 0.
    covered = alpha > 1e-6
    depth = torch.where(covered, depth_sum / torch.where(covered, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(alpha))
    if background is not None:
        color = color + (1.0 - alpha)[..., None] * background.to(color)
    if return_ids and ids is not None and idx is not None:
        ids = torch.where(ids >= 0, idx[ids.clamp(min=0)], ids)
    return RenderOutput(color, depth, alpha, ids if return_ids else None, proj)


def antialias(proj: Projected, eps2d: float = EPS2D) -> Projected:
    """Mip-Splatting's 2D filter (gsplat's "antialiased" mode): the low-pass dilation by eps2d px^2
    keeps each Gaussian's integral instead of its peak, opacity x sqrt(det cov / det (cov + eps2d)),
    so a Gaussian smaller than a pixel in a far view covers the share of the pixel it really does
    instead of a whole pixel. Differentiable through the conics [N, 3] (inverse dilated covariances)."""
    A, B, C = proj.conics.double().unbind(-1)
    det_conic = A * C - B * B
    ok = det_conic > 0
    det_d = torch.where(ok, 1.0 / torch.where(ok, det_conic, torch.ones_like(det_conic)), torch.zeros_like(A))  # det(cov + eps)
    tr_d = (A + C) * det_d                                                                                     # tr(cov + eps)
    det = det_d - eps2d * tr_d + eps2d * eps2d                                                            # det(cov)
    # A flat Gaussian seen edge-on has det 0 (rounding: below): it covers nothing. The guarded
    # sqrt keeps its gradient finite.
    live = ok & (det > 1e-20 * det_d)
    comp = torch.where(live, torch.sqrt(torch.where(live, det / torch.where(ok, det_d, torch.ones_like(det_d)), 1.0)),
                       torch.zeros_like(det)).clamp(max=1.0)
    return Projected(proj.means2d, proj.conics, proj.depths, (proj.opacities * comp.float()), proj.radii)
