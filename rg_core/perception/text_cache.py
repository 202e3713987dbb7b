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


# Embeddings of the fixed lists with the packaged encoder, made at build time by
# scripts/ship_embeddings.py, so that a fresh machine's first query does not embed them.
SHIPPED_DIR = Path(__file__).parent / "data" / "embeddings"


def _key(text_model, texts: list[str], tag: str) -> str:
    ident = model_identity(text_model)
    return f"{tag}_" + hashlib.sha1(("\n".join(texts) + f"|{tag}|{ident}").encode()).hexdigest()[:16]


def _load(p: Path, n: int, dim: int | None) -> torch.Tensor | None:
    """A stored [n, dim] float32 array, or None (missing, unreadable or of another shape)."""
    if not p.is_file():
        return None
    try:
        a = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        log.warning("embedding cache %s unreadable (%s): rebuilding", p, exc)
        return None
    if a.shape[0] == n and a.dtype == np.float32 and (dim is None or a.shape[-1] == dim):
        return torch.from_numpy(a)
    log.warning("embedding cache %s has shape %s for %d texts: rebuilding", p, a.shape, n)
    return None


def embed_cached(text_model, texts: list[str], cache_dir: str | Path | None, tag: str) -> torch.Tensor:
    """Embeddings of a fixed text list (the background, ConSE's 1000 classes): from the package's
    shipped files when they match the texts and the encoder, else from cache_dir, else computed and
    kept there (keyed by a hash of the texts and the encoder's identity: embedding 2000 texts on 2
    cores takes 10-20 s). None cache_dir: nothing is written."""
    key, dim = _key(text_model, texts, tag), getattr(inner_encoder(text_model), "dim", None)
    for folder in (SHIPPED_DIR, cache_dir):
        if folder:
            e = _load(Path(folder).expanduser() / f"{key}.npy", len(texts), dim)
            if e is not None:
                return e
    e = text_model(texts).float()
    if not cache_dir:
        return e
    p = Path(cache_dir).expanduser() / f"{key}.npy"
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_suffix(".tmp.npy")
        np.save(tmp, e.numpy())
        tmp.replace(p)
    except OSError as exc:
        log.warning("embedding cache %s not written (%s)", p, exc)
    return e
