"""Monotone quantile transform of physical mask scales (m) to [0, 1], fitted on supervision scales.

The mappers see scale through this transform (as GARField/ReasonGrounder's code do with a
quantile transformer): scales are spread evenly over [0, 1] whatever the scene's size, and any
input (0, 1e6, NaN) maps to a finite value in [0, 1].
"""
from __future__ import annotations

import torch

_TINY = 1e-6  # m: scales below are treated as this (log stays finite)


class QuantileScale:
    """knots [K] strictly increasing log-scales at quantiles 0, 1/(K-1), ..., 1; piecewise linear between."""

    def __init__(self, knots: torch.Tensor, n_fit: int):
        if knots.ndim != 1 or knots.numel() < 2 or not bool(torch.isfinite(knots).all()):
            raise ValueError(f"QuantileScale: knots must be a finite [K >= 2] vector, got {list(knots.shape)}")
        if not bool((knots[1:] > knots[:-1]).all()):
            raise ValueError("QuantileScale: knots must be strictly increasing")
        self.knots = knots.double()
        self.n_fit = int(n_fit)

    @staticmethod
    def fit(scales: torch.Tensor, n_knots: int = 33) -> QuantileScale:
        """scales [M] (m, > 0 expected; non-finite values are ignored)."""
        s = torch.as_tensor(scales, dtype=torch.float64).reshape(-1)
        s = s[torch.isfinite(s)]
        if s.numel() == 0:
            raise ValueError("QuantileScale.fit: no finite scales to fit (empty supervision?)")
        if n_knots < 2:
            raise ValueError(f"QuantileScale.fit: need at least 2 knots, got {n_knots}")
        x = torch.log(s.clamp(min=_TINY))
        q = torch.quantile(x, torch.linspace(0, 1, n_knots, dtype=torch.float64))
        # Ties (many masks of one scale, or a single mask) would make the map a step: spread the
        # knots by a tiny strictly increasing offset so it stays monotone and invertible.
        q = q + torch.arange(n_knots, dtype=torch.float64) * 1e-4
        q = torch.cummax(q, 0).values
        return QuantileScale(q, int(s.numel()))

    def __call__(self, s) -> torch.Tensor:
        """s (float or tensor [...], m) -> [...] float32 in [0, 1], monotone non-decreasing in s."""
        s = torch.as_tensor(s, dtype=torch.float64)
        x = torch.log(torch.nan_to_num(s, nan=_TINY, posinf=1e30).clamp(min=_TINY))
        k = self.knots
        i = torch.searchsorted(k, x.reshape(-1).contiguous()).clamp(1, len(k) - 1)
        lo, hi = k[i - 1], k[i]
        t = ((x.reshape(-1) - lo) / (hi - lo)).clamp(0.0, 1.0)
        u = ((i - 1).double() + t) / (len(k) - 1)
        return u.reshape(s.shape).float()

    def state_dict(self) -> dict:
        return {"knots": self.knots.clone(), "n_fit": self.n_fit}

    @staticmethod
    def from_state_dict(d: dict) -> QuantileScale:
        return QuantileScale(d["knots"].double(), int(d["n_fit"]))
