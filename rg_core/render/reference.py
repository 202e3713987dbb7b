"""Pure-torch reference rasterizer: clear, slow, the ground truth the fast path is tested against.

Per tile, every pixel evaluates every Gaussian binned to the tile (dense [P, K] tensors) and the
front-to-back compositing with early termination is written with cumprod, so autograd gives the
exact gradients of the same function the C++ kernel computes by hand.
"""
from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected


@torch.no_grad()
def bin_tiles(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, width: int, height: int,
              tile: int) -> tuple[torch.Tensor, torch.Tensor]:
    """-> (offsets [T+1] int64, gaussian ids [M] int64): per tile, ids sorted by (depth, id)."""
    tiles_x, tiles_y = (width + tile - 1) // tile, (height + tile - 1) // tile
    ids = torch.nonzero(radii > 0).squeeze(1)
    r = radii[ids].to(torch.float32)
    u, v = means2d[ids, 0], means2d[ids, 1]
    # Pixel range covered by the footprint square, clipped to the image, then to tiles.
    x0 = torch.ceil(u - r).clamp(0, width - 1).long() // tile
    x1 = torch.floor(u + r).clamp(0, width - 1).long() // tile
    y0 = torch.ceil(v - r).clamp(0, height - 1).long() // tile
    y1 = torch.floor(v + r).clamp(0, height - 1).long() // tile
    nx, ny = (x1 - x0 + 1).clamp(min=0), (y1 - y0 + 1).clamp(min=0)
    counts = nx * ny
    gid = torch.repeat_interleave(ids, counts)
    start = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    local = torch.arange(len(gid)) - start
    nx_r = torch.repeat_interleave(nx, counts)
    tx = torch.repeat_interleave(x0, counts) + local % nx_r
    ty = torch.repeat_interleave(y0, counts) + local // nx_r
    tile_id = ty * tiles_x + tx
    # Sort by (tile, depth, id): stable sorts from the least significant key up.
    order = torch.sort(depths[gid], stable=True).indices
    gid, tile_id = gid[order], tile_id[order]
    order = torch.sort(tile_id, stable=True).indices
    gid, tile_id = gid[order], tile_id[order]
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(torch.bincount(tile_id, minlength=tiles_x * tiles_y), 0)
    return offsets, gid


def _composite_tile(px: torch.Tensor, mu: torch.Tensor, con: torch.Tensor, op: torch.Tensor,
                    ch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """px [P, 2], per-Gaussian mu [K, 2], con [K, 3], op [K], ch [K, C] (front to back)
    -> colour [P, C], final transmittance [P], blending weights [P, K]."""
    d = mu[None, :, :] - px[:, None, :]                      # [P, K, 2]
    dx, dy = d[..., 0], d[..., 1]
    power = -0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) - con[:, 1] * dx * dy
    alpha = torch.clamp(op * torch.exp(power), max=ALPHA_MAX)
    alpha = torch.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    t_after = torch.cumprod(one_minus, dim=1)                 # transmittance after each Gaussian
    t_before = torch.cat([torch.ones_like(t_after[:, :1]), t_after[:, :-1]], 1)
    keep = t_after >= T_MIN                                   # early termination (monotone in K)
    w = torch.where(keep, alpha * t_before, torch.zeros_like(alpha))
    t_final = torch.prod(torch.where(keep, one_minus, torch.ones_like(one_minus)), dim=1)
    return w @ ch, t_final, w


def rasterize_reference(proj: Projected, channels: torch.Tensor, width: int, height: int, tile: int = 16,
                        return_ids: bool = False, checkpoint_tiles: bool = True):
    """-> (colour [H, W, C], alpha [H, W], ids [H, W] int64 or None)."""
    N, C = channels.shape
    offsets, gids = bin_tiles(proj.means2d.detach(), proj.radii, proj.depths.detach(), width, height, tile)
    tiles_x = (width + tile - 1) // tile
    out = channels.new_zeros(height, width, C)
    t_img = channels.new_ones(height, width)
    ids_img = torch.full((height, width), -1, dtype=torch.int64) if return_ids else None
    use_ckpt = checkpoint_tiles and torch.is_grad_enabled()
    rows, cols = [], []
    for t in range(len(offsets) - 1):
        s, e = int(offsets[t]), int(offsets[t + 1])
        if s == e:
            continue
        ty, tx = divmod(t, tiles_x)
        ys = torch.arange(ty * tile, min((ty + 1) * tile, height))
        xs = torch.arange(tx * tile, min((tx + 1) * tile, width))
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        px = torch.stack([gx.reshape(-1), gy.reshape(-1)], 1).to(channels.dtype)
        g = gids[s:e]
        args = (px, proj.means2d[g], proj.conics[g], proj.opacities[g], channels[g])
        if use_ckpt:
            col, tf, w = checkpoint(_composite_tile, *args, use_reentrant=False)
        else:
            col, tf, w = _composite_tile(*args)
        rows.append((gy.reshape(-1), gx.reshape(-1)))
        cols.append((col, tf))
        if return_ids:
            wmax, arg = w.detach().max(dim=1)
            ids_img[gy.reshape(-1), gx.reshape(-1)] = torch.where(wmax > 0, g[arg], torch.full_like(arg, -1))
    if rows:
        yy = torch.cat([r[0] for r in rows])
        xx = torch.cat([r[1] for r in rows])
        out = out.index_put((yy, xx), torch.cat([c[0] for c in cols]))
        t_img = t_img.index_put((yy, xx), torch.cat([c[1] for c in cols]))
    else:
        # Nothing visible: keep the outputs connected to the inputs (zero gradients, no autograd
        # error in a training loop). Empty sums are exactly 0, even for inf/NaN inputs.
        out = out + channels[:0].sum()
        t_img = t_img + proj.opacities[:0].sum()
    return out, 1.0 - t_img, ids_img
