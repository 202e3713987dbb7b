"""The two shallow MLPs shared by all Gaussians: F_l(s, f) (language, PCA space) and F_g(s, f)
(instance, unit-normalised). They take the normalised scale u in [0, 1] and a latent f; applied to
rendered 2D latents for training (cheap: only the sampled pixels) and to per-Gaussian latents for
grouping."""
from __future__ import annotations

import math

import torch
from torch import nn


class ScaleMLP(nn.Module):
    """[..., latent_dim] latent and [...] or scalar normalised scale -> [..., out_dim]."""

    def __init__(self, latent_dim: int, out_dim: int, hidden: int = 64, frequencies: int = 4,
                 unit: bool = False):
        super().__init__()
        self.latent_dim, self.out_dim, self.frequencies, self.unit = latent_dim, out_dim, frequencies, unit
        n_in = latent_dim + 1 + 2 * frequencies
        self.net = nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, out_dim))

    def encode_scale(self, u: torch.Tensor) -> torch.Tensor:  # [...] -> [..., 1 + 2F]
        f = (2.0 ** torch.arange(self.frequencies, dtype=u.dtype, device=u.device)) * math.pi
        a = u[..., None] * f
        return torch.cat([u[..., None], torch.sin(a), torch.cos(a)], -1)

    def forward(self, latent: torch.Tensor, u) -> torch.Tensor:
        if latent.shape[-1] != self.latent_dim:
            raise ValueError(f"mapper: latent must be [..., {self.latent_dim}], got {list(latent.shape)}")
        u = torch.as_tensor(u, dtype=latent.dtype, device=latent.device)
        try:
            u = torch.broadcast_to(u, latent.shape[:-1])
        except RuntimeError as exc:
            raise ValueError(f"mapper: scale must be a scalar or broadcast to {list(latent.shape[:-1])}, "
                             f"got {list(u.shape)}") from exc
        x = torch.cat([latent, self.encode_scale(u)], -1)
        y = self.net(x)
        return nn.functional.normalize(y, dim=-1, eps=1e-8) if self.unit else y


@torch.no_grad()
def sparse_adam_step(param: torch.Tensor, m: torch.Tensor, v: torch.Tensor, t: torch.Tensor,
                     grad: torch.Tensor | None, lr: float) -> int:
    """Adam, in place, on the rows of param [N, D] whose grad [N, D] is non-zero (per-row step counts
    t [N]); the other rows, and their moments m, v [N, D], stay bitwise unchanged. Returns rows moved."""
    if grad is None:
        return 0
    grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
    rows = torch.nonzero((grad != 0).any(1)).squeeze(1)
    if len(rows) == 0:
        return 0
    b1, b2, eps = 0.9, 0.999, 1e-15
    g = grad[rows]
    t[rows] += 1
    tr = t[rows].double()[:, None]
    mr = m[rows].mul_(b1).add_(g, alpha=1 - b1)
    vr = v[rows].mul_(b2).addcmul_(g, g, value=1 - b2)
    m[rows], v[rows] = mr, vr
    upd = (mr / (1 - b1 ** tr).float()) / ((vr / (1 - b2 ** tr).float()).sqrt() + eps)
    param[rows] = param[rows] - lr * upd
    return len(rows)
