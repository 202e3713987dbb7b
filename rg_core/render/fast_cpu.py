"""Fast CPU path: the C++/OpenMP kernels (built at install time) behind torch autograd Functions.

The kernels (csrc/) are plain C++ with a C ABI, loaded with ctypes: no torch headers, so the
set-up compiles them in seconds instead of minutes. This module owns every array: it checks
dtype, shape and contiguity, allocates the outputs with torch and passes raw pointers.
"""
from __future__ import annotations

import ctypes
import importlib.machinery
from pathlib import Path

import torch

from .camera import Camera
from .projection import EPS2D, Projected

# Tests set this: outputs start as NaN, so any element a kernel forgets to write shows.
POISON = False

_LIB_NAME = "_rasterize_cpu"
_lib = None
_IMPORT_ERROR: str = ""

_f32p = ctypes.POINTER(ctypes.c_float)
_f64p = ctypes.POINTER(ctypes.c_double)
_i32p = ctypes.POINTER(ctypes.c_int32)
_i64p = ctypes.POINTER(ctypes.c_int64)
_i64, _int, _dbl = ctypes.c_int64, ctypes.c_int, ctypes.c_double

_SIGNATURES = {
    "rg_project_forward": (None, [_f32p, _f32p, _f32p, _f32p, _i64, _f64p, _f64p, _i64, _i64, _dbl, _dbl, _dbl,
                                  _f32p, _f32p, _f32p, _f32p, _i32p, _int]),
    "rg_project_backward": (None, [_f32p, _f32p, _f32p, _f32p, _i64, _f64p, _f64p, _i64, _i64, _dbl, _dbl, _dbl,
                                   _f32p, _f32p, _f32p, _f32p, _f32p, _f32p, _f32p, _f32p, _int]),
    "rg_bin_count": (_i64, [_f32p, _i32p, _i64, _int, _int, _int, _i32p, _i64p]),
    "rg_bin_fill": (None, [_i32p, _f32p, _i64, _int, _int, _int, _i64p, _i32p, _int]),
    "rg_rasterize_forward": (None, [_f32p, _f32p, _f32p, _f32p, _i64, _i64, _int, _int, _int, _i64p, _i32p,
                                    _f32p, _f32p, _i32p, _i32p, _int]),
    "rg_rasterize_backward": (None, [_f32p, _f32p, _f32p, _f32p, _i64, _i64, _int, _int, _int, _i64p, _i32p,
                                     _f32p, _i32p, _f32p, _f32p, _f32p, _int, _int]),
}


def _load():
    """The built library next to this file (`_rasterize_cpu<ext suffix>`), or None with the reason."""
    global _IMPORT_ERROR
    here = Path(__file__).resolve().parent
    paths = [here / (_LIB_NAME + s) for s in importlib.machinery.EXTENSION_SUFFIXES]
    path = next((p for p in paths if p.is_file()), None)
    if path is None:
        _IMPORT_ERROR = f"no {_LIB_NAME}*.so in {here}"
        return None
    try:
        lib = ctypes.CDLL(str(path))
        for name, (res, args) in _SIGNATURES.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = res, args
    except (OSError, AttributeError) as exc:  # an old build (torch extension) or a broken file
        _IMPORT_ERROR = f"{path.name}: {exc} (rebuild it)"
        return None
    return lib


_lib = _load()


def available() -> bool:
    return _lib is not None


def _require():
    if _lib is None:
        raise RuntimeError(
            "rg_core.render._rasterize_cpu is not built: run `bash scripts/bootstrap.sh` or "
            f"`pip install --no-build-isolation -e .` ({_IMPORT_ERROR})")
    return _lib


def _p(t: torch.Tensor):
    """Raw pointer of a contiguous CPU tensor, typed by its dtype."""
    kind = {torch.float32: _f32p, torch.float64: _f64p, torch.int32: _i32p, torch.int64: _i64p}[t.dtype]
    return ctypes.cast(t.data_ptr(), kind)


def _arr(t: torch.Tensor, dtype: torch.dtype, shape: tuple, name: str) -> torch.Tensor:
    """t as a contiguous CPU tensor of `dtype`, checked against `shape` (-1: any size)."""
    if t.device.type != "cpu":
        raise ValueError(f"fast CPU rasterizer: {name} must be on the CPU, got {t.device}")
    if t.dim() != len(shape) or any(s != -1 and s != d for s, d in zip(shape, t.shape)):
        raise ValueError(f"fast CPU rasterizer: {name} must have shape {list(shape)}, got {list(t.shape)}")
    return t.detach().to(dtype).contiguous()


def _empty(*shape, dtype=torch.float32) -> torch.Tensor:
    if POISON:
        return torch.full(shape, float("nan"), dtype=dtype) if dtype.is_floating_point else \
            torch.full(shape, -7, dtype=dtype)
    return torch.empty(shape, dtype=dtype)


def _threads() -> int:
    return max(1, torch.get_num_threads())


def _cam_args(camera: Camera, eps2d: float):
    w2c = camera.world_to_cam.detach().to(torch.float64).contiguous()   # [4, 4]
    K = camera.K.detach().to(torch.float64).contiguous()                # [3, 3]
    return (w2c, K), (_p(w2c), _p(K), camera.width, camera.height, float(camera.near), float(camera.far),
                      float(eps2d))


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, radii, depths, width, height, tile):
        lib = _require()
        n = means2d.shape[0]
        m2 = _arr(means2d, torch.float32, (n, 2), "means2d")
        cn = _arr(conics, torch.float32, (n, 3), "conics")
        op = _arr(opacities, torch.float32, (n,), "opacities")
        col = _arr(colors, torch.float32, (n, -1), "colors")
        rad = _arr(radii, torch.int32, (n,), "radii")
        dep = _arr(depths, torch.float32, (n,), "depths")
        C = col.shape[1]
        tiles = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        rect = torch.empty(n, 4, dtype=torch.int32)
        offsets = torch.empty(tiles + 1, dtype=torch.int64)
        m = lib.rg_bin_count(_p(m2), _p(rad), n, width, height, tile, _p(rect), _p(offsets))
        gids = torch.empty(m, dtype=torch.int32)
        nt = _threads()
        lib.rg_bin_fill(_p(rect), _p(dep), n, width, height, tile, _p(offsets), _p(gids), nt)
        out, t_final = _empty(height, width, C), _empty(height, width)
        n_contrib, max_id = _empty(height, width, dtype=torch.int32), _empty(height, width, dtype=torch.int32)
        lib.rg_rasterize_forward(_p(m2), _p(cn), _p(op), _p(col), n, C, width, height, tile, _p(offsets),
                                 _p(gids), _p(out), _p(t_final), _p(n_contrib), _p(max_id), nt)
        ctx.save_for_backward(m2, cn, op, col, offsets, gids, t_final, n_contrib)
        ctx.dims = (width, height, tile)
        ctx.mark_non_differentiable(max_id)
        return out, 1.0 - t_final, max_id

    @staticmethod
    def backward(ctx, grad_out, grad_alpha, _grad_ids):
        m2, cn, op, col, offsets, gids, t_final, n_contrib = ctx.saved_tensors
        width, height, tile = ctx.dims
        n, C = col.shape
        g_out = torch.zeros(height, width, C) if grad_out is None else \
            _arr(grad_out, torch.float32, (height, width, C), "grad_out")
        g_alpha = torch.zeros(height, width) if grad_alpha is None else \
            _arr(grad_alpha, torch.float32, (height, width), "grad_alpha")
        # dL/d(alpha) = -dL/d(t_final): the kernel takes the alpha gradient as is
        grads = _empty(n, 6 + C)
        geometry = any(ctx.needs_input_grad[:3])  # a feature render of fixed Gaussians: colour only
        _require().rg_rasterize_backward(_p(m2), _p(cn), _p(op), _p(col), n, C, width, height, tile,
                                         _p(offsets), _p(gids), _p(t_final), _p(n_contrib), _p(g_out),
                                         _p(g_alpha), _p(grads), int(geometry), _threads())
        if not geometry:
            return None, None, None, grads[:, 6:], None, None, None, None, None
        return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:], None, None, None, None, None


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, scales, quats, opacities, camera: Camera, eps2d: float):
        lib = _require()
        n = means.shape[0]
        ins = (_arr(means, torch.float32, (n, 3), "means"), _arr(scales, torch.float32, (n, 3), "scales"),
               _arr(quats, torch.float32, (n, 4), "quats"), _arr(opacities, torch.float32, (n,), "opacities"))
        keep, cam = _cam_args(camera, eps2d)
        means2d, conics, depths, opac = _empty(n, 2), _empty(n, 3), _empty(n), _empty(n)
        radii = _empty(n, dtype=torch.int32)
        lib.rg_project_forward(*(_p(t) for t in ins), n, *cam, _p(means2d), _p(conics), _p(depths), _p(opac),
                               _p(radii), _threads())
        ctx.save_for_backward(*ins)
        ctx.camera, ctx.eps2d = camera, eps2d
        ctx.mark_non_differentiable(radii)
        del keep
        return means2d, conics, depths, opac, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_opac, _g_radii):
        ins = ctx.saved_tensors
        n = ins[0].shape[0]

        def grad(g, shape, name):
            return torch.zeros(shape) if g is None else _arr(g, torch.float32, shape, name)

        gin = (grad(g_means2d, (n, 2), "g_means2d"), grad(g_conics, (n, 3), "g_conics"),
               grad(g_depths, (n,), "g_depths"), grad(g_opac, (n,), "g_opac"))
        keep, cam = _cam_args(ctx.camera, ctx.eps2d)
        gm, gs, gq, go = _empty(n, 3), _empty(n, 3), _empty(n, 4), _empty(n)
        _require().rg_project_backward(*(_p(t) for t in ins), n, *cam, *(_p(t) for t in gin), _p(gm), _p(gs),
                                       _p(gq), _p(go), _threads())
        del keep
        return gm, gs, gq, go, None, None


def project_fast(means, scales, quats, opacities, camera: Camera, eps2d: float = EPS2D) -> Projected:
    """C++ twin of projection.project_gaussians (same outputs and gradients)."""
    m2, cn, d, o, r = _ProjectCPU.apply(means.float(), scales.float(), quats.float(), opacities.float(), camera, eps2d)
    return Projected(means2d=m2, conics=cn, depths=d, opacities=o, radii=r)


def rasterize_fast(proj: Projected, channels: torch.Tensor, width: int, height: int, tile: int = 16):
    """-> (colour [H, W, C], alpha [H, W], ids [H, W] int64), same contract as the reference."""
    out, alpha, ids = _RasterizeCPU.apply(proj.means2d, proj.conics, proj.opacities, channels.float(),
                                          proj.radii, proj.depths.detach(), int(width), int(height), int(tile))
    return out, alpha, ids.long()
