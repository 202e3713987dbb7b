"""OpenCLIP checkpoint (open_clip_config.json + open_clip_model.safetensors / .bin) <-> transformers
CLIPModel, without open_clip (which needs torchvision, unusable here).

The laion hub repositories ship OpenCLIP's own layout; transformers' CLIPModel is the same
architecture (pre-LN ViT image tower with class token, causal text transformer pooled at the
end-of-text token, linear projections without bias), so the weights map one to one: fused
attention in_proj <-> q/k/v projections, `proj` matrices transposed into Linear weights.
`openclip_to_hf` is what export uses; `hf_to_openclip` writes the OpenCLIP layout (tests build
hub-shaped repositories with it).
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from .registry import ModelError

_BLOCK = {  # OpenCLIP residual block -> transformers encoder layer (same tensor layout)
    "ln_1.weight": "layer_norm1.weight", "ln_1.bias": "layer_norm1.bias",
    "ln_2.weight": "layer_norm2.weight", "ln_2.bias": "layer_norm2.bias",
    "attn.out_proj.weight": "self_attn.out_proj.weight", "attn.out_proj.bias": "self_attn.out_proj.bias",
    "mlp.c_fc.weight": "mlp.fc1.weight", "mlp.c_fc.bias": "mlp.fc1.bias",
    "mlp.c_proj.weight": "mlp.fc2.weight", "mlp.c_proj.bias": "mlp.fc2.bias",
}


def hf_config(oc: dict):
    """open_clip_config.json ("model_cfg" or the bare model config) -> transformers CLIPConfig."""
    from transformers import CLIPConfig

    m = oc.get("model_cfg", oc)
    try:
        v, t, embed = m["vision_cfg"], m["text_cfg"], int(m["embed_dim"])
        for k in ("hf_model_name", "timm_model_name"):
            if t.get(k) or v.get(k):
                raise ModelError(f"open_clip config uses {k}: only the built-in CLIP towers convert")
        act = "quick_gelu" if m.get("quick_gelu") else "gelu"
        vw, tw = int(v["width"]), int(t["width"])
        vision = dict(hidden_size=vw, intermediate_size=int(vw * v.get("mlp_ratio", 4.0)),
                      num_hidden_layers=int(v["layers"]), num_attention_heads=vw // int(v.get("head_width", 64)),
                      image_size=int(v["image_size"]), patch_size=int(v["patch_size"]), hidden_act=act,
                      layer_norm_eps=1e-5, projection_dim=embed)
        text = dict(vocab_size=int(t["vocab_size"]), hidden_size=tw, intermediate_size=int(tw * t.get("mlp_ratio", 4.0)),
                    num_hidden_layers=int(t["layers"]), num_attention_heads=int(t.get("heads", 8)),
                    max_position_embeddings=int(t["context_length"]), hidden_act=act, layer_norm_eps=1e-5,
                    eos_token_id=int(t["vocab_size"]) - 1, bos_token_id=int(t["vocab_size"]) - 2,
                    pad_token_id=int(t.get("pad_id", 0)), projection_dim=embed)
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelError(f"open_clip config is not a CLIP ViT config ({type(exc).__name__}: {exc})") from exc
    if vision["num_attention_heads"] < 1:
        raise ModelError(f"open_clip config: vision width {vw} < head_width {v.get('head_width', 64)}")
    return CLIPConfig(text_config=text, vision_config=vision, projection_dim=embed)


_TOWERS = (("vision", "visual.transformer.resblocks.", "vision_model.encoder.layers."),
           ("text", "transformer.resblocks.", "text_model.encoder.layers."))

_TOP = (  # OpenCLIP name, transformers name, transposed (`proj` matrices <-> Linear weights)
    ("visual.class_embedding", "vision_model.embeddings.class_embedding", False),
    ("visual.conv1.weight", "vision_model.embeddings.patch_embedding.weight", False),
    ("visual.positional_embedding", "vision_model.embeddings.position_embedding.weight", False),
    ("visual.ln_pre.weight", "vision_model.pre_layrnorm.weight", False),
    ("visual.ln_pre.bias", "vision_model.pre_layrnorm.bias", False),
    ("visual.ln_post.weight", "vision_model.post_layernorm.weight", False),
    ("visual.ln_post.bias", "vision_model.post_layernorm.bias", False),
    ("visual.proj", "visual_projection.weight", True),
    ("token_embedding.weight", "text_model.embeddings.token_embedding.weight", False),
    ("positional_embedding", "text_model.embeddings.position_embedding.weight", False),
    ("ln_final.weight", "text_model.final_layer_norm.weight", False),
    ("ln_final.bias", "text_model.final_layer_norm.bias", False),
    ("text_projection", "text_projection.weight", True),
    ("logit_scale", "logit_scale", False),
)


def _layer_prefixes(cfg):
    """(OpenCLIP, transformers) key prefixes of every residual block, vision tower then text tower:
    the one walk over the layers that both directions of the conversion share."""
    for tower, pre, hf in _TOWERS:
        for i in range((cfg.vision_config if tower == "vision" else cfg.text_config).num_hidden_layers):
            yield f"{pre}{i}.", f"{hf}{i}."


def _top_level(sd: dict, to_hf: bool) -> dict:
    """The tensors outside the residual blocks (embeddings, pre/post norms, projections,
    logit_scale), renamed by `_TOP` in either direction; the same table serves both."""
    pairs = ((o, h, t) if to_hf else (h, o, t) for o, h, t in _TOP)
    return {dst: sd[src].T if t else sd[src] for src, dst, t in pairs}


def openclip_to_hf(sd: dict, cfg) -> dict:
    """OpenCLIP state dict -> transformers CLIPModel state dict."""
    out = {}
    for p, h in _layer_prefixes(cfg):
        for a, b in _BLOCK.items():
            out[h + b] = sd[p + a]
        for j, (w, bias) in enumerate(zip(sd[p + "attn.in_proj_weight"].chunk(3), sd[p + "attn.in_proj_bias"].chunk(3))):
            out[f"{h}self_attn.{'qkv'[j]}_proj.weight"], out[f"{h}self_attn.{'qkv'[j]}_proj.bias"] = w, bias
    out.update(_top_level(sd, to_hf=True))
    return {k: v.contiguous() for k, v in out.items()}


def hf_to_openclip(sd: dict, cfg) -> dict:
    """transformers CLIPModel state dict -> OpenCLIP state dict (the inverse of openclip_to_hf)."""
    out = {}
    for p, h in _layer_prefixes(cfg):
        for a, b in _BLOCK.items():
            out[p + a] = sd[h + b]
        out[p + "attn.in_proj_weight"] = torch.cat([sd[f"{h}self_attn.{c}_proj.weight"] for c in "qkv"])
        out[p + "attn.in_proj_bias"] = torch.cat([sd[f"{h}self_attn.{c}_proj.bias"] for c in "qkv"])
    out.update(_top_level(sd, to_hf=False))
    return {k: v.contiguous() for k, v in out.items()}


def load_state(path: Path) -> dict:
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path))
    sd = torch.load(str(path), map_location="cpu", weights_only=True)
    return sd.get("state_dict", sd) if isinstance(sd, dict) else sd


def load_openclip_as_hf(config_path: Path, weights_path: Path):
    """-> (transformers CLIPModel in eval mode, open_clip config dict)."""
    from transformers import CLIPModel

    oc = json.loads(Path(config_path).read_text())
    cfg = hf_config(oc)
    sd = load_state(Path(weights_path))
    sd = {k[len("module."):] if k.startswith("module.") else k: v for k, v in sd.items()}
    try:
        hf_sd = openclip_to_hf(sd, cfg)
    except KeyError as exc:
        raise ModelError(f"{weights_path}: not an OpenCLIP ViT checkpoint matching {config_path} (missing {exc})") from exc
    model = CLIPModel(cfg)
    shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    bad = [k for k, v in hf_sd.items() if tuple(v.shape) != shapes.get(k)]
    if bad:
        raise ModelError(f"{weights_path}: tensor shapes differ from {config_path} for {bad[:5]}")
    missing, unexpected = model.load_state_dict(hf_sd, strict=False)
    missing = [k for k in missing if not k.endswith("position_ids")]
    if missing or unexpected:
        raise ModelError(f"{weights_path}: weights do not fit the config (missing {missing[:5]}, unexpected {unexpected[:5]})")
    return model.eval(), oc
