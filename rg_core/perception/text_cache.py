"""Text embeddings kept: in memory per process (CachedText around an encoder: a scene's vocabulary
is embedded once) and on disk for fixed text lists (embed_cached: the background names, ConSE's
1000 classes), keyed by the texts and the encoder's identity."""
from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)


class CachedText:
    """Embedding cache around MiniLMText: a scene's vocabulary is embedded once."""

    def __init__(self, model):
        self.model, self.cache = model, {}

    def __call__(self, texts: list[str]) -> torch.Tensor:
        missing = [t for t in dict.fromkeys(texts) if t not in self.cache]
        if missing:
            for t, e in zip(missing, self.model(missing)):
                self.cache[t] = e
            if len(self.cache) > 20000:
                self.cache = {t: self.cache[t] for t in texts}
        return torch.stack([self.cache[t] for t in texts]) if texts else torch.zeros(0, self.model.dim)


def inner_encoder(text_model):
    """The encoder behind an embedding cache wrapper (CachedText keeps it as .model)."""
    return text_model.model if isinstance(text_model, CachedText) else text_model


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
