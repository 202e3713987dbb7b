"""PCA of mask embeddings (e.g. 512 or 384 -> 64 dims), kept with the map so that rendered 64-d
features decompress back into the embedding space. Refits as new masks arrive."""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class PCA:
    mean: torch.Tensor        # [D]
    components: torch.Tensor  # [k, D], orthonormal rows
    explained_variance_ratio: torch.Tensor  # [k]
    n_fit: int                # number of embeddings it was fitted on

    @staticmethod
    def fit(x: torch.Tensor, k: int = 64) -> "PCA":
        """x [N, D] -> PCA with k components (fewer if N or D is smaller; the rest is zero-padded
        so the compressed size is always k)."""
        if x.ndim != 2 or x.shape[0] < 2 or not bool(torch.isfinite(x).all()):
            raise ValueError(f"PCA.fit: need a finite [N >= 2, D] matrix, got {list(x.shape)}")
        x = x.double()
        mean = x.mean(0)
        xc = x - mean
        _, s, vh = torch.linalg.svd(xc, full_matrices=False)
        var = s ** 2
        total = var.sum().clamp(min=1e-30)
        r = min(k, vh.shape[0])
        comps = torch.zeros(k, x.shape[1], dtype=torch.float64)
        comps[:r] = vh[:r]
        ratio = torch.zeros(k, dtype=torch.float64)
        ratio[:r] = var[:r] / total
        return PCA(mean.float(), comps.float(), ratio.float(), int(x.shape[0]))

    @property
    def dim(self) -> int:
        return self.components.shape[0]

    def transform(self, x: torch.Tensor) -> torch.Tensor:  # [N, D] -> [N, k]
        return (x.float() - self.mean) @ self.components.T

    def inverse(self, z: torch.Tensor) -> torch.Tensor:  # [..., k] -> [..., D]
        return z.float() @ self.components + self.mean

    def state_dict(self) -> dict:
        return {"mean": self.mean, "components": self.components,
                "explained_variance_ratio": self.explained_variance_ratio, "n_fit": self.n_fit}

    @staticmethod
    def from_state_dict(d: dict) -> "PCA":
        return PCA(d["mean"].float(), d["components"].float(), d["explained_variance_ratio"].float(), int(d["n_fit"]))


class IncrementalPCA:
    """Keeps all raw embeddings; refits once `refit_growth` x more have arrived since the last fit,
    so stored supervision can be re-expressed in the new basis (`transform` of the raw rows)."""

    def __init__(self, k: int = 64, refit_growth: float = 1.5, min_fit: int = 8):
        self.k, self.refit_growth, self.min_fit = k, refit_growth, min_fit
        self.raw: list[torch.Tensor] = []
        self.pca: PCA | None = None
        self.version = 0

    def add(self, x: torch.Tensor) -> bool:
        """Add embeddings [N, D]; returns True when the basis was (re)fitted."""
        self.raw.append(x.detach().float())
        n = sum(len(r) for r in self.raw)
        if n < self.min_fit:
            return False
        if self.pca is None or n >= self.refit_growth * self.pca.n_fit:
            self.pca = PCA.fit(torch.cat(self.raw), self.k)
            self.version += 1
            return True
        return False

    def fit_now(self) -> bool:
        """Fit on every embedding so far even below `min_fit` (a finished supervision set: e.g. a
        one-keyframe map of a nearly static camera has 7 masks). True when it fitted."""
        if self.pca is not None or not any(len(r) for r in self.raw):
            return False
        self.pca = PCA.fit(torch.cat(self.raw), self.k)
        self.version += 1
        return True
