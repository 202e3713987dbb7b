"""The model registry: which published weights each backend of the paper's configuration needs,
where they come from (hub repository, revision, files), their licence and size, and where they are
kept on this machine.

Files are fetched into `models_dir() / NAME` (plain files, the repository's own names), the ONNX
exports of `rg models export NAME` go to `models_dir() / NAME / onnx`. Revisions are pinned to a
commit where one was known when the entry was written; otherwise "main" (the fetch manifest then
records the commit actually downloaded). A file entry may be a tuple of alternatives (the first one
the repository holds is used), for repositories that ship the same weights under two names.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..config import CACHE_DIR


class ModelError(ValueError):
    """A model cannot be fetched, exported, verified or used: the message says what and how to fix it."""


class ModelMissingError(ModelError):
    """A model's files are not on this machine: the message names the `rg models ...` command to run."""


class ChecksumError(ModelError):
    """A file's SHA-256 (or git blob hash) differs from the one the hub or the registry states."""


@dataclass(frozen=True)
class ModelSpec:
    name: str
    kind: str
    """"clip" (image + text encoders), "sam" (mask encoder + decoder) or "lvlm" (GGUF + projector)."""
    backend: str
    """Backend that runs it once fetched (and exported): onnx_clip, sam_onnx or llama_cpp."""
    repo_id: str
    revision: str
    files: tuple
    """Files to fetch; an entry may be a tuple of alternative names."""
    licence: str
    size: str
    """Download size as the hub lists it."""
    source: str
    """What it is and why it is here."""
    sha256: dict = field(default_factory=dict)
    """Known SHA-256 per file; files not listed are checked against the hub's own hash (ETag)."""
    cpu: bool = False
    """Small enough for a CPU-only machine."""


MODELS: dict[str, ModelSpec] = {s.name: s for s in (
    ModelSpec(
        "openclip-vit-b16-laion2b", "clip", "onnx_clip", "laion/CLIP-ViT-B-16-laion2B-s34B-b88K",
        "7288da5a0d6f0b51c4a2b27c624837a9236d0112",
        ("open_clip_config.json", ("open_clip_model.safetensors", "open_clip_pytorch_model.bin"), "tokenizer.json"),
        "MIT", "599 MB", "OpenCLIP ViT-B/16 laion2b_s34b_b88k: the image-text model of LangSplat and the paper",
        cpu=True),
    ModelSpec(
        "sam-vit-huge", "sam", "sam_onnx", "facebook/sam-vit-huge", "main",
        ("config.json", ("model.safetensors", "pytorch_model.bin"), "preprocessor_config.json"),
        "Apache-2.0", "2.56 GB", "Segment Anything ViT-H (transformers format): the paper's mask generator"),
    ModelSpec(
        "sam-vit-base", "sam", "sam_onnx", "facebook/sam-vit-base", "main",
        ("config.json", ("model.safetensors", "pytorch_model.bin"), "preprocessor_config.json"),
        "Apache-2.0", "375 MB", "Segment Anything ViT-B (transformers format): smaller SAM"),
    ModelSpec(
        "slimsam-77", "sam", "sam_onnx", "nielsr/slimsam-77-uniform", "main",
        ("config.json", "model.safetensors", "preprocessor_config.json"),
        "Apache-2.0", "38.9 MB", "SlimSAM-77 (SAM ViT-B pruned to 1.4% of SAM-H's parameters; transformers "
        "SamModel format): SAM for a CPU", cpu=True),
    ModelSpec(
        "llava-1.5-7b", "lvlm", "llama_cpp", "mys/ggml_llava-v1.5-7b", "9b713a64048c7f982ec3969e60e9f61f7a2730c2",
        ("ggml-model-q4_k.gguf", "mmproj-model-f16.gguf"),
        "Llama 2 Community Licence (LLaVA)", "4.08 GB + 624 MB projector",
        "LLaVA 1.5 7B GGUF (Q4_K) with its CLIP projector, for llama.cpp: the paper's LVLM family"),
    ModelSpec(
        "smolvlm-256m", "lvlm", "llama_cpp", "ggml-org/SmolVLM-256M-Instruct-GGUF", "main",
        ("SmolVLM-256M-Instruct-Q8_0.gguf", "mmproj-SmolVLM-256M-Instruct-Q8_0.gguf"),
        "Apache-2.0", "about 0.28 GB", "SmolVLM 256M Instruct GGUF (Q8_0) with its projector: an LVLM for a CPU",
        cpu=True),
)}


def models_dir() -> Path:
    """$RG_MODELS_DIR, else ~/.cache/reasongrounder/models."""
    env = os.environ.get("RG_MODELS_DIR")
    return Path(env).expanduser() if env else Path(CACHE_DIR).expanduser() / "models"


def get_spec(name: str) -> ModelSpec:
    if name not in MODELS:
        raise ModelError(f"unknown model {name!r}; known: {', '.join(MODELS)} (rg models list)")
    return MODELS[name]


def model_dir(name: str, root: Path | None = None) -> Path:
    return Path(root or models_dir()) / get_spec(name).name


def onnx_dir(name: str, root: Path | None = None) -> Path:
    return model_dir(name, root) / "onnx"
