"""LERF / LangSplat relevancy: how much more a feature looks like the query than like generic
"canonical" phrases. relevancy = min_c exp(f.q) / (exp(f.q) + exp(f.c_c)), in [0, 1]."""
from __future__ import annotations

import torch

CANONICAL = ("object", "things", "stuff", "texture")


def relevancy(features: torch.Tensor, query: torch.Tensor, canonical: torch.Tensor) -> torch.Tensor:
    """features [..., D] (any norm; normalised here), query [D], canonical [C, D] -> [...] in [0, 1]."""
    if features.shape[-1] != query.shape[-1] or canonical.ndim != 2 or canonical.shape[1] != query.shape[-1]:
        raise ValueError(f"relevancy: features [..., D], query [D], canonical [C, D] with one D; got "
                         f"{list(features.shape)}, {list(query.shape)}, {list(canonical.shape)}")
    f = torch.nn.functional.normalize(features.float(), dim=-1, eps=1e-8)
    q = torch.nn.functional.normalize(query.float(), dim=-1, eps=1e-8)
    c = torch.nn.functional.normalize(canonical.float(), dim=-1, eps=1e-8)
    sq = f @ q                      # [...]
    sc = f @ c.T                    # [..., C]
    # exp(a) / (exp(a) + exp(b)) = sigmoid(a - b): no overflow for any cosine.
    return torch.sigmoid(sq[..., None] - sc).min(-1).values
