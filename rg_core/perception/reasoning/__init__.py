"""Reasoning backends: a query (+ optional scene image) -> the name of the target object.

ReasonGrounder hands implicit queries ("something to drink hot tea from") to an LVLM that names
the object; the name is then grounded in the feature field. Here: the interface (Reasoner,
Reasoning, validate) and the registry. The backends beside it are imported when first made: the
offline default "text" (text.py, with its open-set rejection in open_set.py) and the LLM / LVLM
reasoners (llm.py).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ...config import MAX_QUERY_CHARS
from ..base import BackendError
from ..query import check_query, parse_mode
from ..text_cache import CachedText

__all__ = ["Reasoning", "Reasoner", "TextReasoner", "make_reasoner", "register", "validate", "reasoner_from_config",
           "BackendError"]


@dataclass
class Reasoning:
    target: str                 # a vocabulary name, or "" when nothing in the vocabulary fits
    explanation: str
    confidence: float           # [0, 1]
    implicit: bool
    backend: str
    fallback_reason: str | None = None
    seconds: float = 0.0
    similarity: float = 0.0     # text similarity of query and target (best one when rejected)


def validate(query: str, vocabulary: list[str], max_query_chars: int = MAX_QUERY_CHARS, mode: str = "auto") -> list[str]:
    """Reject unusable input with a message saying what was expected; returns the clean vocabulary
    (stripped, de-duplicated, order kept)."""
    check_query(query, max_query_chars)
    parse_mode(mode)
    if isinstance(vocabulary, str):
        raise ValueError("vocabulary must be a list of object names, got a single string")
    clean = list(dict.fromkeys(v.strip() for v in vocabulary if isinstance(v, str) and v.strip()))
    if not clean:
        raise ValueError("vocabulary is empty: expected at least one object name the map can ground")
    return clean


class Reasoner:
    """Interface: `reason(query, vocabulary, image=None, mode="auto") -> Reasoning`."""

    name = "base"

    def reason(self, query: str, vocabulary: list[str], image: np.ndarray | None = None,
               mode: str = "auto") -> Reasoning:
        raise NotImplementedError

    def load(self) -> None:
        """Load now what `reason` would load on first use (default: nothing)."""


_TEXT = "rg_core.perception.reasoning.text:TextReasoner"   # the built-in offline backend
_REGISTRY: dict[str, Callable[..., Reasoner] | str] = {
    "text": _TEXT,
    "openai": "rg_core.perception.reasoning.llm:OpenAIChatReasoner",
    "llama_cpp": "rg_core.perception.reasoning.llm:LlamaCppReasoner",
}


def _text_reasoner() -> type:
    """The TextReasoner class, imported on first use as the registry's backends are."""
    module, _, attr = _TEXT.partition(":")
    return getattr(importlib.import_module(module), attr)


def __getattr__(name: str):
    """`TextReasoner` is part of this package's API, loaded from text.py when first asked for."""
    if name == "TextReasoner":
        return _text_reasoner()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def register(name: str, factory: Callable[..., Reasoner] | str) -> None:
    """Add a backend: a factory, or "package.module:attr" imported when first made."""
    _REGISTRY[name] = factory


def make_reasoner(name: str = "text", **kwargs) -> Reasoner:
    from ...util import make_registered

    return make_registered("reasoner", _REGISTRY, name, **kwargs)


def _text_kwargs(cfg) -> dict:
    """TextReasoner arguments from a ReasonConfig: its thresholds, or the chosen encoder's own fit
    and open-set prior, and the LLM scorer when configured."""
    text = dict(top_k=cfg.top_k, min_similarity=cfg.min_similarity, absent_margin=cfg.absent_margin,
                max_query_chars=cfg.max_query_chars, extra_vocabulary=list(cfg.extra_vocabulary),
                name_weight=cfg.name_weight, background_exclude=cfg.background_exclude,
                use_knowledge=cfg.use_knowledge, knowledge_path=cfg.knowledge_path, domain_prior=cfg.domain_prior,
                prior_trust=cfg.prior_trust, cache_dir=cfg.cache_dir)
    if cfg.text_model not in ("", "minilm"):
        from ..sentence_text import encoder_fit, make_text_model

        text["text_model"] = CachedText(make_text_model(cfg.text_model, cfg.cache_dir))
        fit, prior = encoder_fit(cfg.text_model)
        text.update(fit)
        if prior is None:
            text["domain_prior"] = False   # the packaged prior is MiniLM's
        else:
            text["domain_prior_path"] = str(prior)
    if cfg.backend == "text" and cfg.llm_scorer and cfg.llm_weight:
        from .llm_scorer import scorer_from_config

        text.update(scorer_from_config(cfg), llm_weight=cfg.llm_weight)
    return text


def reasoner_from_config(cfg) -> Reasoner:
    """Build the reasoner a ReasonConfig (rg_core.config) describes; LLM backends fall back to the
    text reasoner of the same config."""
    text = _text_kwargs(cfg)
    if cfg.backend == "text":
        return make_reasoner("text", **text)
    fallback = _text_reasoner()(**text)
    common = dict(timeout_s=cfg.timeout_s, max_query_chars=cfg.max_query_chars, fallback=fallback)
    if cfg.backend == "openai":
        return make_reasoner("openai", base_url=cfg.openai_base_url, model=cfg.openai_model,
                             api_key=cfg.openai_api_key, accepts_images=cfg.accepts_images, **common)
    if cfg.backend == "llama_cpp":
        return make_reasoner("llama_cpp", model_path=cfg.gguf_path, clip_model_path=cfg.clip_model_path, **common)
    return make_reasoner(cfg.backend, **text)
