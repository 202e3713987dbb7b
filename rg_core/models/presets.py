"""Named configurations: which mask generator, embedder and reasoner a run uses.

- "offline": today's default, nothing to download (RGB-D masks, ConSE over packaged models, the
  MiniLM text reasoner).
- "paper": the paper's backends: SAM ViT-H masks (sam_onnx), OpenCLIP ViT-B/16 laion2b_s34b_b88k
  features (onnx_clip), LLaVA 1.5 7B through llama.cpp for implicit queries.
- "paper_cpu": the same pipeline with models a CPU can run: SlimSAM-77, OpenCLIP ViT-B/16, SmolVLM-256M.
A model that is missing raises ModelMissingError naming the `rg models fetch/export NAME` to run.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .registry import ModelError, ModelMissingError, get_spec, model_dir


@dataclass(frozen=True)
class Preset:
    name: str
    sam: str | None = None
    clip: str | None = None
    lvlm: str | None = None
    description: str = ""


PRESETS: dict[str, Preset] = {p.name: p for p in (
    Preset("offline", description="RGB-D masks + ConSE embeddings + MiniLM text reasoner; no download"),
    Preset("paper", "sam-vit-huge", "openclip-vit-b16-laion2b", "llava-1.5-7b",
           "SAM ViT-H + OpenCLIP ViT-B/16 + LLaVA 1.5 7B (llama.cpp)"),
    Preset("paper_cpu", "slimsam-77", "openclip-vit-b16-laion2b", "smolvlm-256m",
           "SlimSAM-77 + OpenCLIP ViT-B/16 + SmolVLM-256M (llama.cpp): the paper's pipeline on a CPU"),
)}


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ModelError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]


def _root(mcfg) -> Path | None:
    return Path(mcfg.dir).expanduser() if mcfg is not None and mcfg.dir else None


def perception_spec(name: str, mcfg=None) -> tuple[str, dict, str, dict]:
    """-> (mask generator backend, its kwargs, embedder backend, its kwargs). `mcfg`: config.ModelsConfig."""
    from .export import read_export

    p = get_preset(name)
    if p.sam is None:
        return "rgbd", {}, "conse", {}
    root = _root(mcfg)
    for m in (p.sam, p.clip):
        if read_export(m, root) is None:
            raise ModelMissingError(f"preset {name!r} needs {m} ({get_spec(m).source}) exported to ONNX in "
                                    f"{model_dir(m, root) / 'onnx'}; run `rg models fetch {m}` then "
                                    f"`rg models export {m}`")
    sd, cd = model_dir(p.sam, root) / "onnx", model_dir(p.clip, root) / "onnx"
    ci = read_export(p.clip, root)
    threads = mcfg.threads if mcfg is not None else 0
    sam_kw = {"encoder_path": str(sd / "encoder.onnx"), "decoder_path": str(sd / "decoder.onnx"), "threads": threads}
    if mcfg is not None:
        sam_kw.update(points_per_side=mcfg.sam_points_per_side, points_per_batch=mcfg.sam_points_per_batch)
    clip_kw = {"image_model": str(cd / "image.onnx"), "text_model": str(cd / "text.onnx"), "tokenizer_dir": str(cd),
               "image_size": int(ci["image_size"]), "context_length": int(ci["context_length"]), "threads": threads}
    return "sam_onnx", sam_kw, "onnx_clip", clip_kw


def make_perception(name: str, mcfg=None):
    """-> (mask generator, embedder) of a preset."""
    from ..perception.embed import make_embedder
    from ..perception.masks import make_mask_generator

    g, gk, e, ek = perception_spec(name, mcfg)
    return make_mask_generator(g, **gk), make_embedder(e, **ek)


def make_text_encoder(name: str, mcfg=None):
    """The query text encoder that matches the preset's image embeddings (None: the default MiniLM)."""
    g, gk, e, ek = perception_spec(name, mcfg)
    if e == "conse":
        return None
    from ..perception.embed import make_embedder

    return make_embedder(e, **ek).encode_texts


def apply_reasoner(name: str, cfg) -> None:
    """Point cfg.reason at the preset's LVLM (llama.cpp GGUF + projector); "offline" leaves it alone."""
    p = get_preset(name)
    if p.lvlm is None:
        return
    root = _root(cfg.models)
    spec = get_spec(p.lvlm)
    paths = [model_dir(p.lvlm, root) / f for f in spec.files]
    missing = [str(x) for x in paths if not x.is_file()]
    if missing:
        raise ModelMissingError(f"preset {name!r} reasons with {p.lvlm} ({spec.source}); {missing[0]} is missing: "
                                f"run `rg models fetch {p.lvlm}` (or pass --backend text to reason without it)")
    cfg.reason.backend, cfg.reason.gguf_path, cfg.reason.clip_model_path = "llama_cpp", str(paths[0]), str(paths[1])
