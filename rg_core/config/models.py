"""Section of the named model presets and the model cache (rg_core/models)."""
from __future__ import annotations

from typing import Annotated

from annotated_types import Interval

from .schema import section


@section
class ModelsConfig:
    """Named model configurations and the model cache (`rg models ...`, `--preset`; rg_core/models)."""

    preset: str = "offline"
    """"offline" (RGB-D masks, ConSE, text reasoner: no download), "paper" (SAM ViT-H + OpenCLIP
    ViT-B/16 + LLaVA 1.5 via llama.cpp) or "paper_cpu" (SlimSAM-77 + OpenCLIP + SmolVLM-256M)."""
    dir: str = ""
    """Model cache; empty = $RG_MODELS_DIR or ~/.cache/reasongrounder/models."""
    sam_points_per_side: int = 32
    """SAM automatic masks: point grid per side (SamAutomaticMaskGenerator's default)."""
    sam_points_per_batch: int = 64
    """SAM prompts per decoder call."""
    threads: int = 0
    """onnxruntime intra-op threads of the exported models (0 = its default)."""
    views_per_object: Annotated[int, Interval(ge=0)] = 3
    """Default supervision embeds each object (its masks associated across keyframes) in at most this
    many views, the largest first; its other masks take the object's mean (0: every mask)."""
