"""The field's two losses on sampled pixels of one view, as pure functions (gradient-checked).

- L_lang: Huber(F_l(s_i, f_p), z_i) over (pixel p, mask i) with p in mask i, at mask i's scale,
- L_in: GARField's scale-conditioned contrastive loss on pixel pairs of one view: a pair shares a
  group at scale s if some mask with scale <= s contains both; such pairs are pulled together
  (distance), all other pairs pushed apart to at least the margin (hinge).
"""
from __future__ import annotations

import torch


def language_loss(pred: torch.Tensor, target: torch.Tensor, delta: float) -> torch.Tensor:
    """pred, target [Q, D] (one row per pixel and scale) -> scalar: Huber summed over D, mean over Q
    (a mean over D would shrink the loss with the PCA size and let L_in drown it)."""
    if pred.shape != target.shape or pred.ndim != 2:
        raise ValueError(f"language_loss: pred {list(pred.shape)} and target {list(target.shape)} must be equal [Q, D]")
    if delta <= 0:
        raise ValueError(f"language_loss: delta must be > 0, got {delta}")
    if pred.shape[0] == 0:
        return pred.sum() * 0.0
    return torch.nn.functional.huber_loss(pred, target.to(pred), delta=delta, reduction="none").sum(1).mean()


def shares_group(members: torch.Tensor, mask_scales: torch.Tensor, s: float) -> torch.Tensor:
    """members [P, M] bool (pixel in mask), mask_scales [M] -> [P, P] bool: some mask with scale <= s
    holds both pixels (GARField's group definition; a pixel in no such mask is its own group)."""
    if members.ndim != 2 or mask_scales.shape != (members.shape[1],):
        raise ValueError(f"shares_group: members [P, M] and scales [M], got {list(members.shape)}, "
                         f"{list(mask_scales.shape)}")
    a = (members & (mask_scales <= s)[None, :]).float()  # [P, M]
    return (a @ a.T) > 0


def language_targets(members: torch.Tensor, mask_scales: torch.Tensor, targets: torch.Tensor,
                     s: float) -> torch.Tensor:
    """Target of each pixel at scale s: the embedding of its group at s (the largest mask with
    scale <= s holding it); 0 (the PCA mean: "no group at this scale") where there is none.
    members [P, M] bool, mask_scales [M], targets [M, D] -> [P, D]. At s = s_i this is z_i on mask
    i's pixels (the loss of the issue); the other pixels keep F_l from answering by scale alone."""
    if members.ndim != 2 or mask_scales.shape != (members.shape[1],) or targets.shape[0] != members.shape[1]:
        raise ValueError(f"language_targets: members [P, M], scales [M], targets [M, D], got "
                         f"{list(members.shape)}, {list(mask_scales.shape)}, {list(targets.shape)}")
    ok = members & (mask_scales <= s)[None, :]  # [P, M]
    if members.shape[1] == 0:
        return torch.zeros(members.shape[0], targets.shape[1], dtype=targets.dtype)
    score = torch.where(ok, mask_scales[None, :].to(torch.float64), torch.full(ok.shape, -1.0, dtype=torch.float64))
    j = score.argmax(1)
    return torch.where(ok.any(1, keepdim=True), targets[j], torch.zeros((), dtype=targets.dtype))


def instance_loss(feat: torch.Tensor, share: torch.Tensor, margin: float) -> torch.Tensor:
    """feat [P, Di] instance features of P pixels of one view at one scale, share [P, P] bool ->
    scalar: mean distance over sharing pairs + mean hinge(margin - distance) over the others
    (upper triangle only: each unordered pair once, no self-pairs)."""
    P = feat.shape[0]
    if feat.ndim != 2 or share.shape != (P, P):
        raise ValueError(f"instance_loss: feat [P, Di] and share [P, P], got {list(feat.shape)}, {list(share.shape)}")
    if margin <= 0:
        raise ValueError(f"instance_loss: margin must be > 0, got {margin}")
    if P < 2:
        return feat.sum() * 0.0
    sq = (feat * feat).sum(1)
    d2 = (sq[:, None] + sq[None, :] - 2.0 * feat @ feat.T).clamp(min=0.0)  # [P, P], one matmul
    # sqrt(x + eps): finite gradient when two features coincide (pulled pairs reach zero distance).
    dist = torch.sqrt(d2 + 1e-12)
    upper = torch.ones(P, P, dtype=torch.bool, device=feat.device).triu(1)
    pos, neg = upper & share, upper & ~share
    n_pos, n_neg = int(pos.sum()), int(neg.sum())
    zero = torch.zeros((), dtype=feat.dtype)
    l_pos = (dist * pos).sum() / n_pos if n_pos else zero
    l_neg = (torch.relu(margin - dist) * neg).sum() / n_neg if n_neg else zero
    return l_pos + l_neg + feat.sum() * 0.0
