"""Which Gaussians leave the map: eviction at `max_gaussians` (the least useful the camera does not
see first; protected boxes stay) and pruning (transparent, oversized or broken). Pure choices: the
Mapper removes them from the map and its optimiser."""
from __future__ import annotations

import numpy as np
import torch

from ..geometry.conventions import in_image, project
from .gaussians import PARAMS, GaussianModel


def protected_box(lo: np.ndarray, hi: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The box lo..hi [3] grown by margin (m); ValueError unless both corners are finite [3]."""
    lo, hi = np.asarray(lo, np.float64) - margin, np.asarray(hi, np.float64) + margin
    if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError(f"protect: a box needs finite lo, hi [3], got {lo}, {hi}")
    return lo, hi


@torch.no_grad()
def eviction_order(g: GaussianModel, n: int, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
                   near: float, protected: list[tuple[np.ndarray, np.ndarray]]) -> torch.Tensor:
    """Up to `n` indices of Gaussians of g the camera (K [3, 3], cam_to_world [4, 4], image size) does
    not see, the least useful first: the lowest opacity x nearness to the camera (median distance /
    (median + distance)) x recency (0.5 + 0.5 rank / N: the map keeps its Gaussians in the order
    they were added). Gaussians in view and in `protected` boxes (lo, hi) are never chosen."""
    means = g.means.detach()
    pts = means.double().numpy()
    uv, z = project(pts, np.asarray(K, np.float64), np.asarray(cam_to_world, np.float64))
    seen = in_image(uv, z, width, height, near)
    d = torch.from_numpy(np.linalg.norm(pts - np.asarray(cam_to_world, np.float64)[:3, 3], axis=1)).float()
    med = d.median().clamp(min=1e-3)
    value = g.opacities.detach() * med / (med + d) * (0.5 + 0.5 * torch.arange(len(g)) / len(g))
    value = torch.nan_to_num(value, nan=-1.0)   # broken Gaussians first
    value[torch.from_numpy(seen)] = float("inf")
    for lo, hi in protected:
        lo_t, hi_t = torch.as_tensor(lo, dtype=means.dtype), torch.as_tensor(hi, dtype=means.dtype)
        value[((means >= lo_t) & (means <= hi_t)).all(1)] = float("inf")
    order = torch.argsort(value)[:n]
    return order[torch.isfinite(value[order])]


@torch.no_grad()
def prune_keep(g: GaussianModel, prune_opacity: float, prune_scale: float) -> torch.Tensor:
    """[N] bool: the Gaussians pruning keeps (finite, opacity above prune_opacity, largest axis
    below prune_scale m)."""
    finite = torch.stack([torch.isfinite(getattr(g, k)).reshape(len(g), -1).all(1) for k in PARAMS]).all(0)
    return finite & (g.opacities > prune_opacity) & (g.scales.max(1).values < prune_scale)
