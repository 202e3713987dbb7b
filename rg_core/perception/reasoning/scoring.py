"""Candidate scoring of the text reasoner (issue 15): one score per vocabulary name from
- name similarity: MiniLM(query) . MiniLM("a {name}")
- gloss similarity: MiniLM(query) . MiniLM("{name}: {WordNet gloss} (a kind of ...)")
- optionally an LLM's log-likelihood of the name as the answer (log-softmax over the names),
combined linearly with weights fit on the tune half of the description set (rg_core/eval/reasoning.py);
and the open-set test: a background concept (ImageNet class or COCO category, by the same two
similarities) unlike every vocabulary name that beats the best name by more than a margin.

The same functions score a reasoner's query and the benchmark's whole tune half at once, so
what is fit is what runs.
"""
from __future__ import annotations

import torch
NAME_TEMPLATE = "a {}"


def combine(s_name: torch.Tensor, s_gloss: torch.Tensor | None, name_weight: float,
            llm: torch.Tensor | None = None, llm_weight: float = 0.0) -> torch.Tensor:
    """[..., N] scores: name_weight * s_name + (1 - name_weight) * s_gloss (+ llm_weight *
    log-softmax of the LLM's log-likelihoods over the same names). Without gloss: s_name."""
    s = s_name if s_gloss is None else name_weight * s_name + (1.0 - name_weight) * s_gloss
    if llm is not None and llm_weight:
        ll = torch.as_tensor(llm, dtype=s.dtype)
        ll = torch.nan_to_num(ll, nan=-1e4, neginf=-1e4, posinf=1e4)
        s = s + llm_weight * torch.log_softmax(ll, dim=-1)
    return s


def background_keep(name_emb_vocab: torch.Tensor, name_emb_bg: torch.Tensor, exclude: float) -> torch.Tensor:
    """[B] bool: background concepts whose name is unlike every vocabulary name (a near-synonym,
    "coffee mug" beside "mug", is the same object, not evidence of absence)."""
    if not len(name_emb_vocab):
        return torch.ones(len(name_emb_bg), dtype=torch.bool)
    return (name_emb_bg @ name_emb_vocab.T).max(1).values < exclude
