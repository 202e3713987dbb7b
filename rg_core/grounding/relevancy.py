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


def relevancy_pca(z: torch.Tensor, components: torch.Tensor, mean: torch.Tensor, query: torch.Tensor,
                  canonical: torch.Tensor) -> torch.Tensor:
    """relevancy(z @ components + mean, query, canonical) without decompressing: z [..., k] PCA
    codes, components [k, D], mean [D]. Dot products and norms of the decompressed features come
    from k-d algebra (Gram matrix of the components), so a 320x240 view never holds [h, w, D]."""
    k, D = components.shape
    if z.shape[-1] != k or mean.shape != (D,) or query.shape != (D,) or canonical.ndim != 2 or canonical.shape[1] != D:
        raise ValueError(f"relevancy_pca: z [..., k], components [k, D], mean [D], query [D], canonical [C, D]; got "
                         f"{list(z.shape)}, {list(components.shape)}, {list(mean.shape)}, {list(query.shape)}, "
                         f"{list(canonical.shape)}")
    C = components.double()
    mu = mean.double()
    texts = torch.nn.functional.normalize(torch.cat([query[None], canonical]).double(), dim=-1, eps=1e-8)  # [1+C, D]
    zf = z.double()
    dots = zf @ (C @ texts.T) + texts @ mu                                   # [..., 1+C]
    n2 = ((zf @ (C @ C.T)) * zf).sum(-1) + 2.0 * zf @ (C @ mu) + mu @ mu      # [...] = |z C + mu|^2
    cos = dots / n2.clamp(min=0.0).sqrt().clamp(min=1e-8)[..., None]
    return torch.sigmoid(cos[..., :1] - cos[..., 1:]).min(-1).values.float()
