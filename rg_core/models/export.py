"""`rg models export NAME`: the fetched PyTorch weights -> ONNX files the onnxruntime backends load.

CLIP (onnx_clip): image.onnx (pixel values [N, 3, S, S], CLIP-normalised -> embeddings [N, D]),
text.onnx (token ids [N, L] int64 -> [N, D]), vocab.json + merges.txt (CLIP's BPE, taken from the
repository's tokenizer.json), export.json (image size, context length, dim).
SAM (sam_onnx): encoder.onnx ([1, 3, 1024, 1024] SAM-normalised -> image embeddings [1, C, 64, 64])
and decoder.onnx with segment_anything's SamOnnxModel signature (image_embeddings, point_coords,
point_labels, mask_input, has_mask_input, orig_im_size -> masks [B, 3, H, W] logits at the original
size, iou_predictions [B, 3], low_res_masks [B, 3, 256, 256]), written here over transformers'
SamModel (no segment_anything, no torchvision). Both use the legacy TorchScript exporter (opset 17),
as the project's tests do.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from .fetch import fetched_file
from .registry import ModelError, get_spec, model_dir, onnx_dir

OPSET = 17


class ClipImageTower(torch.nn.Module):
    """pixel_values [N, 3, S, S] -> projected image embeddings [N, D] (not normalised)."""

    def __init__(self, clip):
        super().__init__()
        self.vision, self.proj = clip.vision_model, clip.visual_projection

    def forward(self, pixel_values):
        return self.proj(self.vision(pixel_values=pixel_values).pooler_output)


class ClipTextTower(torch.nn.Module):
    """input_ids [N, L] int64 -> projected text embeddings [N, D] (pooled at the end-of-text token)."""

    def __init__(self, clip):
        super().__init__()
        self.text, self.proj = clip.text_model, clip.text_projection

    def forward(self, input_ids):
        return self.proj(self.text(input_ids=input_ids).pooler_output)


class SamEncoder(torch.nn.Module):
    def __init__(self, sam):
        super().__init__()
        self.vision = sam.vision_encoder

    def forward(self, image):  # [1, 3, 1024, 1024] -> [1, C, 64, 64]
        return self.vision(image).last_hidden_state


def sam_mask_postprocess(masks, orig_im_size, size: int = 1024):
    """segment_anything's ONNX mask_postprocessing: low-res [B, K, 256, 256] -> [B, K, H, W]."""
    masks = F.interpolate(masks, size=(size, size), mode="bilinear", align_corners=False)
    s = orig_im_size.to(torch.float32)
    pre = torch.floor(size / torch.max(s) * s + 0.5).to(torch.int64)
    masks = masks[..., : pre[0], : pre[1]]
    hw = orig_im_size.to(torch.int64)
    return F.interpolate(masks, size=(hw[0], hw[1]), mode="bilinear", align_corners=False)


class SamDecoder(torch.nn.Module):
    """SamOnnxModel's signature over transformers' SamModel prompt encoder and mask decoder. Points are
    in the 1024 frame; label -1 marks padding points (not-a-point embedding), as SAM's ONNX model."""

    def __init__(self, sam):
        super().__init__()
        self.sam = sam

    def forward(self, image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size):
        pe = self.sam.prompt_encoder
        sparse = pe._embed_points(point_coords[None], point_labels[None], pad=False)  # [1, B, N, C]
        dense = has_mask_input * pe.mask_embed(mask_input) + \
            (1 - has_mask_input) * pe.no_mask_embed.weight.reshape(1, -1, 1, 1)  # [1, C, 64, 64]
        pos = self.sam.get_image_wide_positional_embeddings()  # [1, C, 64, 64]
        low, iou = self.sam.mask_decoder(image_embeddings=image_embeddings, image_positional_embeddings=pos,
                                         sparse_prompt_embeddings=sparse, dense_prompt_embeddings=dense,
                                         multimask_output=True)
        low, iou = low[0], iou[0]  # [B, 3, 256, 256], [B, 3]
        return sam_mask_postprocess(low, orig_im_size), iou, low


def load_clip(name: str, root: Path | None = None):
    """-> (transformers CLIPModel, open_clip config dict) from the fetched OpenCLIP files."""
    from .clip_convert import load_openclip_as_hf

    spec = get_spec(name)
    if spec.kind != "clip":
        raise ModelError(f"{name} is a {spec.kind} model, not CLIP")
    return load_openclip_as_hf(fetched_file(name, "open_clip_config.json", root),
                               fetched_file(name, spec.files[1], root))


def load_sam(name: str, root: Path | None = None):
    from transformers import SamModel

    spec = get_spec(name)
    if spec.kind != "sam":
        raise ModelError(f"{name} is a {spec.kind} model, not SAM")
    fetched_file(name, "config.json", root)
    fetched_file(name, spec.files[1], root)
    try:
        return SamModel.from_pretrained(str(model_dir(name, root)), local_files_only=True).eval()
    except (OSError, ValueError) as exc:
        raise ModelError(f"{name}: transformers could not load SAM from {model_dir(name, root)} ({exc})") from exc


def write_clip_tokenizer(tokenizer_json: Path, out: Path) -> None:
    """CLIP's BPE (vocab.json + merges.txt, what CLIPTokenizer reads) out of a tokenizer.json."""
    data = json.loads(Path(tokenizer_json).read_text())
    model = data.get("model", {})
    if model.get("type") != "BPE" or "vocab" not in model or "merges" not in model:
        raise ModelError(f"{tokenizer_json}: not a BPE tokenizer.json (model.type {model.get('type')!r})")
    merges = [m if isinstance(m, str) else " ".join(m) for m in model["merges"]]
    (out / "vocab.json").write_text(json.dumps(model["vocab"], ensure_ascii=False))
    (out / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + ("\n" if merges else ""))


def _export(module, args, path: Path, inputs, outputs, axes) -> None:
    with torch.no_grad():
        torch.onnx.export(module, args, str(path), input_names=inputs, output_names=outputs, dynamic_axes=axes,
                          opset_version=OPSET, dynamo=False)


def export_clip(name: str, root: Path | None = None) -> dict:
    clip, oc = load_clip(name, root)
    out = onnx_dir(name, root)
    out.mkdir(parents=True, exist_ok=True)
    size = clip.config.vision_config.image_size
    ctx = clip.config.text_config.max_position_embeddings
    _export(ClipImageTower(clip).eval(), (torch.randn(2, 3, size, size),), out / "image.onnx", ["pixel_values"],
            ["embeds"], {"pixel_values": {0: "n"}, "embeds": {0: "n"}})
    ids = torch.randint(0, clip.config.text_config.vocab_size - 1, (2, ctx))
    _export(ClipTextTower(clip).eval(), (ids,), out / "text.onnx", ["input_ids"], ["embeds"],
            {"input_ids": {0: "n"}, "embeds": {0: "n"}})
    write_clip_tokenizer(fetched_file(name, "tokenizer.json", root), out)
    info = {"kind": "clip", "image_size": size, "context_length": ctx, "dim": clip.config.projection_dim,
            "files": ["image.onnx", "text.onnx", "vocab.json", "merges.txt"],
            "mean": oc.get("preprocess_cfg", {}).get("mean"), "std": oc.get("preprocess_cfg", {}).get("std")}
    return info


def export_sam(name: str, root: Path | None = None) -> dict:
    sam = load_sam(name, root)
    out = onnx_dir(name, root)
    out.mkdir(parents=True, exist_ok=True)
    _export(SamEncoder(sam).eval(), (torch.randn(1, 3, 1024, 1024),), out / "encoder.onnx", ["image"],
            ["image_embeddings"], None)
    C = sam.config.prompt_encoder_config.hidden_size
    E = sam.config.prompt_encoder_config.image_embedding_size
    args = (torch.randn(1, C, E, E), torch.rand(2, 2, 2) * 1000, torch.tensor([[1.0, -1.0]] * 2),
            torch.zeros(1, 1, 4 * E, 4 * E), torch.zeros(1), torch.tensor([96.0, 128.0]))
    axes = {"point_coords": {0: "b", 1: "n"}, "point_labels": {0: "b", 1: "n"}, "masks": {0: "b", 2: "h", 3: "w"},
            "iou_predictions": {0: "b"}, "low_res_masks": {0: "b"}}
    _export(SamDecoder(sam).eval(), args, out / "decoder.onnx",
            ["image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size"],
            ["masks", "iou_predictions", "low_res_masks"], axes)
    return {"kind": "sam", "embed_dim": C, "embed_size": E, "files": ["encoder.onnx", "decoder.onnx"]}


def export(name: str, root: Path | None = None) -> dict:
    spec = get_spec(name)
    t0 = time.perf_counter()
    if spec.kind == "clip":
        info = export_clip(name, root)
    elif spec.kind == "sam":
        info = export_sam(name, root)
    else:
        raise ModelError(f"{name}: a {spec.kind} model runs as GGUF in llama.cpp; there is nothing to export "
                         f"(rg models verify {name} checks the files)")
    info.update(name=name, opset=OPSET, seconds=round(time.perf_counter() - t0, 2), dir=str(onnx_dir(name, root)))
    (onnx_dir(name, root) / "export.json").write_text(json.dumps(info, indent=1))
    return info


def read_export(name: str, root: Path | None = None) -> dict | None:
    p = onnx_dir(name, root) / "export.json"
    if not p.is_file():
        return None
    info = json.loads(p.read_text())
    if all((p.parent / f).is_file() for f in info.get("files", [])):
        return info
    return None
