"""The offline default reasoner "text": each vocabulary name is scored by the similarity of the
query to the name and to the name's WordNet knowledge text (a packaged sentence model in place of
the paper's LVLM); an open-set prior and background concepts (open_set.py) reject queries nothing
in the vocabulary fits. Weights and thresholds (FIT) come from the tune half of the description set
(benchmarks/bench_reasoning.py --fit). Explicit queries (they name a vocabulary entry, by rule) pass
straight through.
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np
import torch

from ...config import CACHE_DIR, MAX_QUERY_CHARS
from . import Reasoner, Reasoning, _text_kwargs, open_set, validate
from .explicit import EXPLICIT_SIMILARITY, explicit_match
from .open_set import COCO_NAMES, background_names, load_domain_prior
from ..text_cache import CachedText, embed_cached, inner_encoder

log = logging.getLogger(__name__)
# Fit on the tune half of the description set (benchmarks/bench_reasoning.py --fit; provenance in
# rg_core/config.py ReasonConfig): weight of name similarity against gloss similarity, the floor
# under the best text score, the background margin, and when a background name counts as a synonym.
FIT = {"name_weight": 0.5, "min_similarity": 0.0, "absent_margin": 0.35, "background_exclude": 0.6,
       "prior_trust": 0.4}

NAME_TEMPLATE = "a {}"          # measured: 57/101 top-1 vs 51/101 for bare names
CONFIDENCE_SCALE = 0.05         # confidence = 1 - exp(-margin / scale): margin 0.05 -> 0.63


_SHARED_TEXT = None


def shared_text_model():
    """One MiniLM per process (loading takes seconds; every reasoner can use the same one)."""
    global _SHARED_TEXT
    if _SHARED_TEXT is None:
        from ..embed import MiniLMText

        _SHARED_TEXT = CachedText(MiniLMText())
    return _SHARED_TEXT


def forget_text_embeddings() -> None:
    """Empty this process's text embeddings (MiniLM's KNOWN and the shared reasoner cache). Texts are
    embedded in batches whose padding changes their float rounding, so a scene evaluated after others
    in one process got slightly other embeddings than in a fresh one; many-scene tasks start from
    here, and a scene's figures are then the same in any process, after any other scene."""
    from ..minilm import KNOWN

    KNOWN.clear()
    if _SHARED_TEXT is not None:
        _SHARED_TEXT.cache.clear()


class TextReasoner(Reasoner):
    """Offline default: each vocabulary name scored by MiniLM similarity of the query to the name
    and to the name's WordNet knowledge text (+ an optional LLM scorer's log-likelihoods), with
    open-set rejection against background concepts; weights and thresholds fit on the tune half of
    the description set (rg_core/config.py ReasonConfig, benchmarks/bench_reasoning.py)."""

    name = "text"

    def __init__(self, top_k: int = 3, min_similarity: float = FIT["min_similarity"],
                 absent_margin: float = FIT["absent_margin"], max_query_chars: int = MAX_QUERY_CHARS,
                 extra_vocabulary: list[str] | tuple[str, ...] = (), text_model=None,
                 name_weight: float = FIT["name_weight"], background_exclude: float = FIT["background_exclude"],
                 use_knowledge: bool = True, knowledge_path: str = "", cache_dir: str = CACHE_DIR,
                 llm_scorer=None, llm_weight: float = 0.0, domain_prior: bool = True, domain_prior_path: str = "",
                 prior_trust: float = FIT["prior_trust"]):
        if not 0.0 <= name_weight <= 1.0:
            raise ValueError(f"name_weight must be in [0, 1], got {name_weight}")
        self.text = text_model or shared_text_model()
        self.top_k, self.min_similarity, self.absent_margin = top_k, min_similarity, absent_margin
        self.max_query_chars = max_query_chars
        self.extra = [v for v in extra_vocabulary if v.strip()]
        self.name_weight, self.background_exclude, self.cache_dir = name_weight, background_exclude, cache_dir
        self.llm_scorer, self.llm_weight = llm_scorer, float(llm_weight)
        self.knowledge, self.knowledge_error = None, None
        if use_knowledge:
            from ..knowledge import KnowledgeError, load_knowledge
            try:
                self.knowledge = load_knowledge(knowledge_path or None)
            except KnowledgeError as exc:  # the reasoner still answers, by names alone
                self.knowledge_error = str(exc)
                log.warning("text reasoner without name knowledge: %s", exc)
        self.prior, self.prior_error, self.prior_trust = None, None, prior_trust
        if domain_prior:
            try:
                self.prior = load_domain_prior(domain_prior_path or None)
            except ValueError as exc:  # the reasoner still answers, without the open-set prior
                self.prior_error = str(exc)
                log.warning("text reasoner without open-set prior: %s", exc)
        dim = getattr(inner_encoder(self.text), "dim", None)
        if self.prior is not None and dim is not None and len(self.prior.coef) != dim:
            self.prior_error = (f"open-set prior {domain_prior_path or open_set.DOMAIN_PRIOR_PATH} is "
                                f"{len(self.prior.coef)}-d, the text model {dim}-d: fit one for this encoder "
                                f"(bench_reasoning.py --fit --text-model)")
            log.warning("text reasoner without open-set prior: %s", self.prior_error)
            self.prior = None
        self._bg_on = absent_margin is not None and absent_margin >= 0
        self._bg = None

    def load(self) -> None:
        load = getattr(inner_encoder(self.text), "load", None)
        if load is not None:
            load()

    @classmethod
    def from_config(cls, cfg) -> "TextReasoner":
        """The text reasoner a ReasonConfig describes (encoder, its fit and prior, LLM scorer)."""
        return cls(**_text_kwargs(cfg))

    def vocabulary(self, vocabulary: list[str]) -> list[str]:
        return list(dict.fromkeys(list(vocabulary) + self.extra))

    def gloss_texts(self, names: list[str]) -> list[str]:
        return [self.knowledge.text(n) for n in names] if self.knowledge else []

    def background(self):
        """(names [B], name embeddings [B, D], gloss embeddings [B, D] or None), built once."""
        if self._bg is None:
            if self.knowledge:
                names = [e["name"] for e in self.knowledge.imagenet]
                glosses = self.knowledge.imagenet_texts()
                seen = set(names)
                for n in COCO_NAMES:
                    if n not in seen:
                        names.append(n), glosses.append(self.knowledge.text(n))
            else:
                names, glosses = background_names(), None
            ne = embed_cached(self.text, [NAME_TEMPLATE.format(b) for b in names], self.cache_dir, "bg_names")
            ge = embed_cached(self.text, glosses, self.cache_dir, "bg_glosses") if glosses else None
            self._bg = (names, ne, ge)
        return self._bg

    def scores(self, query: str, vocab: list[str]) -> dict:
        """Evidence per name: name similarity [N], gloss similarity [N] (or None), LLM
        log-likelihoods [N] (or None, with the reason in 'llm_error'), combined text score and
        final score [N]."""
        from .scoring import combine
        q = self.text([query.strip()])
        sn = (q @ self.text([NAME_TEMPLATE.format(v) for v in vocab]).T)[0]
        sg = (q @ self.text(self.gloss_texts(vocab)).T)[0] if self.knowledge else None
        out = {"q": q, "name": sn, "gloss": sg, "llm": None, "llm_error": None}
        out["text"] = combine(sn, sg, self.name_weight)
        if self.llm_scorer is not None and self.llm_weight:
            try:
                ll = self.llm_scorer.score(query, vocab, {v: t for v, t in zip(vocab, self.gloss_texts(vocab))}
                                           if self.knowledge else None)
                ll = torch.as_tensor(np.asarray(ll, np.float64), dtype=sn.dtype)
                if ll.shape != sn.shape:
                    raise ValueError(f"LLM scorer returned shape {tuple(ll.shape)} for {len(vocab)} names")
                out["llm"] = ll
            except Exception as exc:  # noqa: BLE001 - a failing LLM leaves the text evidence
                out["llm_error"] = f"{type(exc).__name__}: {exc}"
                log.warning("LLM scorer failed, text evidence only: %s", out["llm_error"])
        out["score"] = combine(sn, sg, self.name_weight, out["llm"], self.llm_weight)
        return out

    def _absent(self, q: torch.Tensor, vocab: list[str], best_text: float) -> tuple[str, float] | None:
        """The background concept the query resembles more than any vocabulary name, if any."""
        if not self._bg_on:
            return None
        from .scoring import background_keep, combine
        names, ne, ge = self.background()
        keep = background_keep(self.text([NAME_TEMPLATE.format(v) for v in vocab]), ne, self.background_exclude)
        if not keep.any():
            return None
        s = combine((q @ ne.T)[0], (q @ ge.T)[0] if ge is not None else None, self.name_weight)
        s = torch.where(keep, s, torch.full_like(s, -2.0))
        i = int(s.argmax())
        if float(s[i]) - best_text > self.absent_margin:
            return names[i], float(s[i])
        return None

    def reason(self, query: str, vocabulary: list[str], image: np.ndarray | None = None,
               mode: str = "auto") -> Reasoning:
        t0 = time.perf_counter()
        vocab = self.vocabulary(validate(query, vocabulary, self.max_query_chars, mode))
        named = explicit_match(query, vocab) if mode != "implicit" else []
        if named and mode != "explicit":   # a rule match needs no model at all (<= 5 ms)
            r = self._explicit(query, vocab, named, None)
            r.seconds = time.perf_counter() - t0
            return r
        q_bare = self.text([query.strip()])
        bare_sims = (q_bare @ self.text(vocab).T)[0]
        if mode == "auto" and not named and float(bare_sims.max()) >= EXPLICIT_SIMILARITY:
            named = [vocab[int(bare_sims.argmax())]]
        if named or mode == "explicit":
            r = self._explicit(query, vocab, named, bare_sims)
        else:
            r = self._implicit(query, vocab)
        r.seconds = time.perf_counter() - t0
        return r

    def _explicit(self, query: str, vocab: list[str], named: list[str], sims: torch.Tensor | None) -> Reasoning:
        if named:
            if sims is None and len(named) > 1:
                sims = (self.text([query.strip()]) @ self.text(named).T)[0]
                idx = list(range(len(named)))
                best = max(idx, key=lambda i: float(sims[i]))
                pick, sim = named[best], float(sims[best])
            elif sims is None:
                pick, sim = named[0], 1.0
            else:
                best = max((vocab.index(n) for n in named), key=lambda i: float(sims[i]))
                pick, sim = vocab[best], float(sims[best])
            others = [n for n in named if n != pick]
            tail = f"; also matches {', '.join(repr(o) for o in others)}" if others else ""
            return Reasoning(pick, f"explicit query names {pick!r}{tail}", 1.0 / len(named), False, self.name,
                             similarity=sim)
        i = int(sims.argmax())  # forced explicit without a rule match: nearest by bare text
        s = float(sims[i])
        if s < self.min_similarity:
            return Reasoning("", f"explicit query matches no vocabulary name (nearest {vocab[i]!r} at "
                                 f"{s:.2f} < min_similarity {self.min_similarity:.2f})", 0.0, False, self.name,
                             similarity=s)
        return Reasoning(vocab[i], f"explicit query taken as nearest name {vocab[i]!r} (similarity {s:.2f})",
                         s, False, self.name, similarity=s)

    def _evidence(self, ev: dict, i: int) -> str:
        parts = [f"name {float(ev['name'][i]):.2f}"]
        if ev["gloss"] is not None:
            parts.append(f"gloss {float(ev['gloss'][i]):.2f}")
        if ev["llm"] is not None:
            parts.append(f"LLM log-likelihood {float(ev['llm'][i]):.2f}")
        return ", ".join(parts)

    def _implicit(self, query: str, vocab: list[str]) -> Reasoning:
        ev = self.scores(query, vocab)
        sims = ev["score"]
        order = sims.argsort(descending=True).tolist()
        best, s1 = vocab[order[0]], float(sims[order[0]])
        s2 = float(sims[order[1]]) if len(order) > 1 else s1 - 1.0
        best_text = float(ev["text"].max())
        runners = ", ".join(f"{vocab[i]!r} {float(sims[i]):.2f}" for i in order[1:1 + self.top_k])
        ranking = (f"nearest name {best!r} (score {s1:.2f}: {self._evidence(ev, order[0])})"
                   + (f" ahead of {runners}" if runners else ""))
        notes = "".join(f"; {k} unavailable: {v}" for k, v in
                        (("name knowledge", self.knowledge_error), ("open-set prior", self.prior_error),
                         ("LLM evidence", ev["llm_error"])) if v)
        sim = float(ev["name"][order[0]])
        if best_text < self.min_similarity:
            return Reasoning("", f"nothing in the vocabulary fits: {ranking}, text score {best_text:.2f} below "
                                 f"min_similarity {self.min_similarity:.2f}{notes}", 0.0, True, self.name, similarity=sim)
        if self.prior is not None and best_text < self.prior_trust:
            p = self.prior.probability(ev["q"][0])
            if p < self.prior.threshold:
                return Reasoning("", f"nothing in the vocabulary fits: the query does not read like a table-top "
                                     f"object (open-set prior {p:.2f} < {self.prior.threshold:.2f}); {ranking}{notes}",
                                 0.0, True, self.name, similarity=sim)
        absent = self._absent(ev["q"], vocab, best_text)
        if absent:
            return Reasoning("", f"nothing in the vocabulary fits: the query is closer to {absent[0]!r} "
                                 f"({absent[1]:.2f}), which is not in the vocabulary, than to the {ranking}{notes}",
                             0.0, True, self.name, similarity=sim)
        conf = 1.0 - math.exp(-(s1 - s2) / CONFIDENCE_SCALE)
        return Reasoning(best, f"implicit query: {ranking}{notes}", float(min(1.0, max(0.0, conf))), True, self.name,
                         similarity=sim)
