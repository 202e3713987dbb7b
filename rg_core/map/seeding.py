"""Where new Gaussians go: one seed per stride x stride block of candidate pixels (finer on far
surfaces), back-projected and sized by the block's footprint; the detail pixels and the coarse
Gaussians densification adds and splits there; the local range of an image (depth steps, which the
mapper's depth test must not trust). Pure functions: the Mapper applies them to its map."""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry.conventions import project
from ..render import RenderOutput


def local_range(img: torch.Tensor, k: int, valid: torch.Tensor) -> torch.Tensor:
    """Max minus min of img [h, w] over the `valid` [h, w] pixels of each k x k window: [h, w]
    (0 where a window holds no valid pixel)."""
    x, v = img[None, None].float(), valid[None, None]                          # [1, 1, h, w]
    hi = F.max_pool2d(torch.where(v, x, torch.full_like(x, -1e6)), k, 1, k // 2)
    lo = -F.max_pool2d(torch.where(v, -x, torch.full_like(x, -1e6)), k, 1, k // 2)
    return (hi - lo).clamp(min=0)[0, 0]


def seed_pixels(mask: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows, cols) [n] of one pixel of bool mask [h, w] per stride x stride block holding any: the
    one closest to the block centre, so thin regions (object rims) are never skipped."""
    vs, us = torch.nonzero(mask, as_tuple=True)
    if not len(vs):
        return vs, us
    s = stride
    w_blocks = (mask.shape[1] + s - 1) // s
    block = (vs // s) * w_blocks + (us // s)
    centre = (s - 1) / 2.0
    dist = (vs % s - centre) ** 2 + (us % s - centre) ** 2
    order = torch.argsort(block * (2 * s * s + 1) + dist.round().long(), stable=True)
    block, vs, us = block[order], vs[order], us[order]
    first = torch.ones_like(block, dtype=torch.bool)
    first[1:] = block[1:] != block[:-1]
    return vs[first], us[first]


def seed_candidates(mask: torch.Tensor, depth: torch.Tensor, fx: float, stride: int,
                    spacing: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(rows, cols, strides) [n] of the seeds of bool mask [h, w] (seed_pixels). With `spacing` > 0
    (m) and stride > 1, pixels whose stride x stride block spans more than `spacing` at `depth`
    [h, w] (focal length fx px) are seeded at half the stride."""
    s = stride
    if spacing > 0 and s > 1:
        far = depth * (s / fx) > spacing                                             # [h, w]: a block spans more
        regions = [(mask & far, s // 2), (mask & ~far, s)]
    else:
        regions = [(mask, s)]
    picked = [(*seed_pixels(m, st), st) for m, st in regions]                      # (rows, cols, stride)
    vs = torch.cat([p[0] for p in picked])
    us = torch.cat([p[1] for p in picked])
    strides = torch.cat([torch.full((len(p[0]),), float(p[2]), dtype=torch.float64) for p in picked])
    return vs, us, strides


def back_project(vs: torch.Tensor, us: torch.Tensor, strides: torch.Tensor, depth: torch.Tensor, K: np.ndarray,
                 cam_to_world: np.ndarray, seed_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [n, 3] (float64) of pixels (vs, us) [n] at `depth` [h, w] (K [3, 3], cam_to_world
    [4, 4]) and their scales [n]: seed_scale x the footprint of a stride x stride block there."""
    K = torch.as_tensor(K, dtype=torch.float64)
    z = depth[vs, us].double()
    pc = torch.stack([(us.double() - K[0, 2]) * z / K[0, 0], (vs.double() - K[1, 2]) * z / K[1, 1], z], 1)
    c2w = torch.as_tensor(cam_to_world)
    pw = pc @ c2w[:3, :3].T + c2w[:3, 3]
    # Scale from the local point spacing: the footprint of a stride x stride block at depth z.
    return pw, seed_scale * strides * z / K[0, 0]


def detail_pixels(out: RenderOutput, rgb: torch.Tensor, depth: torch.Tensor, background: torch.Tensor,
                  colour_error: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Where a render `out` of a view (rgb [h, w, 3], sensor depth [h, w]) shows a surface in the
    wrong colour (L1 over `background` above colour_error): (depth [h, w]: the sensor's, else the
    rendered surface's; detail [h, w] bool)."""
    valid = depth > 0
    covered = out.alpha > 0.5
    depth = torch.where(valid, depth, out.depth / out.alpha.clamp(min=1e-6))
    err = (out.channels + (1.0 - out.alpha)[..., None] * background - rgb).abs().mean(-1)
    return depth, (valid | covered) & (depth > 0) & (err > colour_error)


def coarse_gaussians(means: torch.Tensor, scales: torch.Tensor, ids: torch.Tensor, K: np.ndarray,
                     cam_to_world: np.ndarray, near: float, split_px: float, room: int) -> torch.Tensor:
    """Of the Gaussians ids [M] (unique, >= 0; means, scales [N, 3]), those whose largest axis spans
    more than split_px pixels in the view (K, cam_to_world): the widest `room` first."""
    _, z = project(means[ids].double().numpy(), np.asarray(K, np.float64), np.asarray(cam_to_world, np.float64))
    z = torch.from_numpy(z).clamp(min=near)                                                  # [M] metres
    span = scales[ids].max(1).values.double() * float(K[0, 0]) / z                          # [M] px
    wide = span > split_px
    return ids[wide][torch.argsort(span[wide], descending=True)][:room]
