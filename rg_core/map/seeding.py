"""Where new Gaussians go: one seed per stride x stride block of candidate pixels; the local range
of an image (depth steps, which the mapper's depth test must not trust)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


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
