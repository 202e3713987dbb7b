"""Fast CPU path: the C++/OpenMP kernel (built at install time) behind a torch autograd Function."""
from __future__ import annotations

import torch

from .camera import Camera
from .projection import Projected

try:  # built by `pip install -e .` (setup.py); absent in a plain source checkout
    from . import _rasterize_cpu as _ext
except ImportError as exc:  # pragma: no cover - depends on the install
    _ext = None
    _IMPORT_ERROR = exc


# Tests set this: outputs start as NaN inside the kernel, so any element it forgets to write shows.
POISON = False


def available() -> bool:
    return _ext is not None


def _require():
    if _ext is None:
        raise RuntimeError(
            "rg_core.render._rasterize_cpu is not built: run `bash scripts/bootstrap.sh` or "
            f"`pip install --no-build-isolation -e .` (import error: {_IMPORT_ERROR})")
    return _ext


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, radii, depths, width, height, tile):
        ext = _require()
        out, t_final, n_contrib, max_id, offsets, gids = ext.rasterize_forward(
            means2d, conics, opacities, colors, radii, depths, width, height, tile, POISON)
        ctx.save_for_backward(means2d, conics, opacities, colors, offsets, gids, t_final, n_contrib)
        ctx.dims = (width, height, tile)
        ctx.mark_non_differentiable(max_id)
        return out, 1.0 - t_final, max_id

    @staticmethod
    def backward(ctx, grad_out, grad_alpha, _grad_ids):
        means2d, conics, opacities, colors, offsets, gids, t_final, n_contrib = ctx.saved_tensors
        width, height, tile = ctx.dims
        if grad_out is None:
            grad_out = torch.zeros(height, width, colors.shape[1])
        if grad_alpha is None:
            grad_alpha = torch.zeros(height, width)
        g_m, g_c, g_o, g_col = _require().rasterize_backward(
            means2d, conics, opacities, colors, offsets, gids, t_final, n_contrib,
            grad_out.float(), grad_alpha.float(), width, height, tile, POISON)
        return g_m, g_c, g_o, g_col, None, None, None, None, None


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, scales, quats, opacities, camera: Camera, eps2d: float):
        dims = (camera.world_to_cam, camera.K, camera.width, camera.height, camera.near, camera.far, eps2d)
        means2d, conics, depths, opac, radii = _require().project_forward(means, scales, quats, opacities, *dims)
        ctx.save_for_backward(means, scales, quats, opacities)
        ctx.dims = dims
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, opac, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_opac, _g_radii):
        means, scales, quats, opacities = ctx.saved_tensors
        zeros = lambda t, shape: torch.zeros(shape) if t is None else t  # noqa: E731
        n = means.shape[0]
        gm, gs, gq, go = _require().project_backward(
            means, scales, quats, opacities, *ctx.dims, zeros(g_means2d, (n, 2)), zeros(g_conics, (n, 3)),
            zeros(g_depths, (n,)), zeros(g_opac, (n,)))
        return gm, gs, gq, go, None, None


def project_fast(means, scales, quats, opacities, camera: Camera, eps2d: float = 0.3) -> Projected:
    """C++ twin of projection.project_gaussians (same outputs and gradients)."""
    m2, cn, d, o, r = _ProjectCPU.apply(means.float(), scales.float(), quats.float(), opacities.float(), camera, eps2d)
    return Projected(means2d=m2, conics=cn, depths=d, opacities=o, radii=r)


def rasterize_fast(proj: Projected, channels: torch.Tensor, width: int, height: int, tile: int = 16):
    """-> (colour [H, W, C], alpha [H, W], ids [H, W] int64), same contract as the reference."""
    out, alpha, ids = _RasterizeCPU.apply(proj.means2d, proj.conics, proj.opacities, channels.float(),
                                          proj.radii, proj.depths.detach(), width, height, tile)
    return out, alpha, ids.long()
