"""Random Gaussian scenes for renderer tests."""
from __future__ import annotations

import torch

from rg_core.render import Camera


def pinhole(width: int, height: int, f: float | None = None, near: float = 0.05, far: float = 50.0,
            w2c: torch.Tensor | None = None) -> Camera:
    f = f if f is not None else 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2 - 0.5], [0.0, f, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return Camera(K, torch.eye(4) if w2c is None else w2c, width, height, near, far)


def random_gaussians(n: int, channels: int, gen: torch.Generator, depth: float = 3.0, spread=(0.6, 0.45, 0.3),
                     scale=(0.005, 0.05)):
    means = torch.randn(n, 3, generator=gen) * torch.tensor(spread) + torch.tensor([0.0, 0.0, depth])
    scales = torch.rand(n, 3, generator=gen) * (scale[1] - scale[0]) + scale[0]
    quats = torch.randn(n, 4, generator=gen)
    opac = torch.rand(n, generator=gen)
    feats = torch.randn(n, channels, generator=gen)
    return [means, scales, quats, opac, feats]


def leaves(params):
    return [p.detach().clone().requires_grad_(True) for p in params]


def render_with_grads(params, cam, backend, seed_weights=0, **kw):
    """Render and backprop a loss touching every output; -> (RenderOutput, grads list)."""
    from rg_core.render import rasterize

    ps = leaves(params)
    out = rasterize(*ps, cam, backend=backend, **kw)
    g = torch.Generator().manual_seed(seed_weights)
    wc = torch.randn(out.channels.shape, generator=g)
    wd = torch.randn(out.depth.shape, generator=g)
    wa = torch.randn(out.alpha.shape, generator=g)
    ((out.channels * wc).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()).backward()
    # No dependence at all (nothing visible) gives None in autograd: the same as a zero gradient.
    return out, [torch.zeros_like(p) if p.grad is None else p.grad for p in ps]
