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

import hashlib
import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)
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


def inner_encoder(text_model):
    """The encoder behind an embedding cache wrapper (reasoner._CachedText keeps it as .model)."""
    from .reasoner import _CachedText   # reasoner imports this module: import at call time

    return text_model.model if isinstance(text_model, _CachedText) else text_model


def model_identity(text_model) -> str:
    """What a stored embedding depends on besides its text: the encoder's class, model folder name
    and width (without it, embeddings of one encoder were served to another from the disk cache)."""
    m = inner_encoder(text_model)
    folder = getattr(m, "folder", None) or getattr(m, "model_name", None) or ""
    return f"{type(m).__name__}:{Path(str(folder)).name}:{getattr(m, 'dim', '')}"


def embed_cached(text_model, texts: list[str], cache_dir: str | Path | None, tag: str) -> torch.Tensor:
    """Embeddings of a fixed text list (the background, ConSE's 1000 classes), kept on disk under
    cache_dir keyed by a hash of the texts: they depend only on the texts and the model, and
    embedding 2000 texts on 2 cores takes 10-20 s. A missing, unreadable or stale cache is rebuilt."""
    if not cache_dir:
        return text_model(texts)
    ident = model_identity(text_model)
    key = hashlib.sha1(("\n".join(texts) + f"|{tag}|{ident}").encode()).hexdigest()[:16]
    p = Path(cache_dir).expanduser() / f"{tag}_{key}.npy"
    if p.is_file():
        try:
            a = np.load(p, allow_pickle=False)
            dim = getattr(inner_encoder(text_model), "dim", None)
            if a.shape[0] == len(texts) and a.dtype == np.float32 and (dim is None or a.shape[-1] == dim):
                return torch.from_numpy(a)
            log.warning("embedding cache %s has shape %s for %d texts: rebuilding", p, a.shape, len(texts))
        except (OSError, ValueError) as exc:
            log.warning("embedding cache %s unreadable (%s): rebuilding", p, exc)
    e = text_model(texts).float()
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_suffix(".tmp.npy")
        np.save(tmp, e.numpy())
        tmp.replace(p)
    except OSError as exc:
        log.warning("embedding cache %s not written (%s)", p, exc)
    return e
