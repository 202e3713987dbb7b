"""What a training step of the field draws from: a keyframe's training view (its masks at the
training resolution, ray weights over its pixels, the held-out pixels it never trains on), the
keyframe (mostly the recent window) and the scales (GARField's interval sampling). Pure functions:
the field passes its supervision, config and random generator."""
from __future__ import annotations

import numpy as np
import torch

from ..config import FieldConfig
from .converge import holdout_pixels


def training_view(sup, index: int, w: int, h: int, tw: int, th: int,
                  cfg: FieldConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Keyframe `index`'s supervision `sup` (masks at w x h) at tw x th: masks [M, th*tw], scales [M],
    ray weights [th*tw] and held-out pixels [th*tw] (converge.py measures the stop test there)."""
    masks = torch.from_numpy(np.asarray(sup.masks, bool))
    if masks.shape[1:] != (h, w):
        raise ValueError(f"field: keyframe {index} masks are {list(masks.shape[1:])}, image is {[h, w]}")
    rows = ((torch.arange(th) + 0.5) * h / th).long().clamp(max=h - 1)  # nearest resampling
    cols = ((torch.arange(tw) + 0.5) * w / tw).long().clamp(max=w - 1)
    masks = masks[:, rows][:, :, cols].reshape(len(masks), th * tw)
    scales = torch.from_numpy(np.asarray(sup.scales, np.float32))
    # Ray weights: mask_ray_fraction spread equally over the masks (each uniformly over
    # its pixels), the rest uniform over the image; drawn without replacement.
    a = min(max(cfg.mask_ray_fraction, 0.0), 1.0) if len(masks) else 0.0
    mf = masks.float()
    weights = (1 - a) / (th * tw) + a * (mf / mf.sum(1, keepdim=True).clamp(min=1)).sum(0) / max(len(masks), 1)
    return masks, scales, weights, holdout_pixels(th * tw, cfg.holdout, cfg.seed, index)


def sample_keyframe(kfs: list, window: int, revisit: float, rng: torch.Generator):
    """One of the supervised keyframes `kfs`: with probability `revisit` (when there are more than
    `window`) one older than the last `window`, else one of them."""
    n = len(kfs)
    if n > window and float(torch.rand(1, generator=rng)) < revisit:
        return kfs[int(torch.randint(0, n - window, (1,), generator=rng))]
    lo = max(0, n - window)
    return kfs[int(torch.randint(lo, n, (1,), generator=rng))]


def sample_scale(scales: torch.Tensor, rng: torch.Generator) -> float:
    """GARField's interval sampling: a mask scale of the view, moved up towards the next one."""
    u = torch.unique(scales[torch.isfinite(scales)]).double()
    if len(u) == 0:
        return 0.0
    j = int(torch.randint(0, len(u), (1,), generator=rng))
    return float(u[j] + float(torch.rand(1, generator=rng)) * (_next_scale(u, j) - u[j]))


def _next_scale(u: torch.Tensor, j: int) -> torch.Tensor:
    """The top of the interval sample_scale draws from above u[j] (u [K] sorted unique scales)."""
    return u[j + 1] if j + 1 < len(u) else u[j] * 1.5


def interval_centre(scales, s: float) -> float:
    """The middle of the interval sample_scale draws from above scale s among a view's mask scales
    [M] (s itself one of them): where the field learned the groups that masks of scale s make. At s
    itself the instance features sit on the step between the scales just below, where those masks
    do not group, and above, where they do: a near-tie the smallest change in training can flip."""
    u = torch.unique(torch.as_tensor(np.asarray(scales, np.float32))).double()
    u = u[torch.isfinite(u)]
    j = int(torch.searchsorted(u, torch.tensor(float(np.float32(s)), dtype=torch.float64)))
    if j >= len(u) or float(u[j]) != float(np.float32(s)):
        return float(s)   # not a scale of the view: no interval to centre on
    return float((u[j] + _next_scale(u, j)) / 2)
