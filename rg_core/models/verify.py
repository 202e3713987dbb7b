"""`rg models verify NAME`: load what `fetch` and `export` wrote, run a known input, check it.

Checks: the fetched files still match the hashes of the fetch manifest; the ONNX backends load
through their real loading paths (OnnxClipEmbedder, SamOnnxGenerator) and give the expected shapes,
finite values and unit-norm embeddings; when the PyTorch weights are present, the ONNX outputs match
PyTorch on the same input within the stated tolerances (PARITY). GGUF models: files hashed and their
GGUF magic checked (loading them needs llama.cpp, see the llama_cpp backend).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .export import ClipImageTower, ClipTextTower, SamDecoder, SamEncoder, load_clip, load_sam, read_export
from .fetch import _check, read_manifest
from .registry import ModelError, ModelMissingError, get_spec, model_dir, onnx_dir

PARITY = {"clip_embedding_max_abs": 1e-4, "sam_embedding_rel": 1e-3, "sam_logit_rel": 1e-3, "sam_iou_abs": 1e-3}
"""ONNX vs PyTorch: CLIP unit embeddings differ by at most 1e-4 per component; SAM image embeddings
and mask logits by at most 1e-3 x max(1, largest magnitude); predicted IoU by 1e-3."""


def known_image(h: int = 96, w: int = 128) -> np.ndarray:
    """Grey background, a red box, a green disc, a blue bar (uint8 [H, W, 3])."""
    img = np.full((h, w, 3), 90, np.uint8)
    img[h // 10:h // 2, w // 12:w // 2] = (220, 40, 40)
    yy, xx = np.mgrid[:h, :w]
    img[(yy - 0.62 * h) ** 2 + (xx - 0.7 * w) ** 2 < (0.23 * h) ** 2] = (40, 200, 60)
    img[int(0.78 * h):int(0.92 * h), w // 25:w - w // 25] = (30, 30, 210)
    return img


KNOWN_TEXTS = ["a red box", "a green ball", "a blue bar on a table"]


def _need_export(name: str, root) -> dict:
    info = read_export(name, root)
    if info is None:
        raise ModelMissingError(f"{name}: no ONNX export in {onnx_dir(name, root)}; run `rg models export {name}`"
                                f" (after `rg models fetch {name}`)")
    return info


def _hash_check(name: str, root) -> dict:
    man = read_manifest(name, root)
    if man is None:
        return {"fetched": False}
    for fname, rec in man["files"].items():
        p = model_dir(name, root) / fname
        if not p.is_file():
            raise ModelMissingError(f"{name}: {fname} was fetched but is gone from {p.parent}; run `rg models fetch {name}`")
        _check(p, rec["sha256"], "the fetch manifest")
    return {"fetched": True, "files_hashed": len(man["files"])}


def make_onnx_clip(name: str, root: Path | None = None, threads: int = 0):
    """The onnx_clip embedder over `rg models export NAME`'s files."""
    from ..perception.embed import OnnxClipEmbedder

    info = _need_export(name, root)
    d = onnx_dir(name, root)
    return OnnxClipEmbedder(str(d / "image.onnx"), str(d / "text.onnx"), str(d), image_size=int(info["image_size"]),
                            context_length=int(info["context_length"]), threads=threads)


def verify_clip(name: str, root) -> dict:
    info = _need_export(name, root)
    emb = make_onnx_clip(name, root)
    img = known_image()
    crops = [img, img[:48, :64].copy(), np.ascontiguousarray(img[::-1])]
    e_img, e_txt = emb.encode_images(crops), emb.encode_texts(KNOWN_TEXTS)
    D = int(info["dim"])
    rep = {"image_embeddings": list(e_img.shape), "text_embeddings": list(e_txt.shape)}
    if e_img.shape != (3, D) or e_txt.shape != (3, D):
        raise ModelError(f"{name}: ONNX CLIP gave image {tuple(e_img.shape)} and text {tuple(e_txt.shape)}, expected (3, {D})")
    for what, e in (("image", e_img), ("text", e_txt)):
        if not torch.isfinite(e).all() or not torch.allclose(e.norm(dim=-1), torch.ones(len(e)), atol=1e-4):
            raise ModelError(f"{name}: ONNX CLIP {what} embeddings are not finite unit vectors")
    try:
        clip, _ = load_clip(name, root)
    except ModelMissingError:
        rep["parity"] = "skipped: PyTorch weights not present"
        return rep
    ids, _ = emb.tokenize(KNOWN_TEXTS)
    with torch.no_grad():
        r_img = torch.nn.functional.normalize(ClipImageTower(clip)(torch.from_numpy(emb.preprocess(crops))), dim=-1)
        r_txt = torch.nn.functional.normalize(ClipTextTower(clip)(torch.from_numpy(ids)), dim=-1)
    d_img, d_txt = float((e_img - r_img).abs().max()), float((e_txt - r_txt).abs().max())
    rep["parity"] = {"image_max_abs": d_img, "text_max_abs": d_txt, "tolerance": PARITY["clip_embedding_max_abs"]}
    if max(d_img, d_txt) > PARITY["clip_embedding_max_abs"]:
        raise ModelError(f"{name}: ONNX and PyTorch CLIP differ (image {d_img:.2e}, text {d_txt:.2e} > "
                         f"{PARITY['clip_embedding_max_abs']:.0e}); run `rg models export {name}` again")
    return rep


def verify_sam(name: str, root) -> dict:
    from ..perception.masks.sam import SamOnnxGenerator, point_grid, preprocess

    info = _need_export(name, root)
    d = onnx_dir(name, root)
    gen = SamOnnxGenerator(str(d / "encoder.onnx"), str(d / "decoder.onnx"), points_per_side=2)
    img = known_image()
    H, W = img.shape[:2]
    emb = gen.embed(img)
    C, E = int(info["embed_dim"]), int(info["embed_size"])
    pts = point_grid(2) * np.array([W, H])  # [4, 2]
    logits, iou = gen.predict_points(emb, pts, (H, W))
    rep = {"image_embeddings": list(emb.shape), "masks": list(logits.shape), "iou": list(iou.shape)}
    if emb.shape != (1, C, E, E) or logits.shape != (4, 3, H, W) or iou.shape != (4, 3):
        raise ModelError(f"{name}: ONNX SAM gave embeddings {emb.shape}, masks {logits.shape}, iou {iou.shape}; "
                         f"expected (1, {C}, {E}, {E}), (4, 3, {H}, {W}), (4, 3)")
    if not (np.isfinite(emb).all() and np.isfinite(logits).all() and np.isfinite(iou).all()):
        raise ModelError(f"{name}: ONNX SAM outputs are not finite")
    try:
        sam = load_sam(name, root)
    except ModelMissingError:
        rep["parity"] = "skipped: PyTorch weights not present"
        return rep
    from ..perception.masks.sam import resized_shape

    rh, rw = resized_shape(H, W)
    coords = (pts * np.array([rw / W, rh / H])).astype(np.float32)
    with torch.no_grad():
        r_emb = SamEncoder(sam)(torch.from_numpy(preprocess(img)))
        r_masks, r_iou, _ = SamDecoder(sam)(
            r_emb, torch.from_numpy(np.concatenate([coords[:, None], np.zeros((4, 1, 2), np.float32)], 1)),
            torch.tensor([[1.0, -1.0]] * 4), torch.zeros(1, 1, 4 * E, 4 * E), torch.zeros(1), torch.tensor([H, W], dtype=torch.float32))
    def rel(a, b):
        return float(np.abs(a - b).max() / max(1.0, np.abs(b).max()))
    p = {"embedding_rel": rel(emb, r_emb.numpy()), "logit_rel": rel(logits, r_masks.numpy()),
         "iou_max_abs": float(np.abs(iou - r_iou.numpy()).max()), "tolerance": PARITY}
    rep["parity"] = p
    if p["embedding_rel"] > PARITY["sam_embedding_rel"] or p["logit_rel"] > PARITY["sam_logit_rel"] \
            or p["iou_max_abs"] > PARITY["sam_iou_abs"]:
        raise ModelError(f"{name}: ONNX and PyTorch SAM differ beyond tolerance ({p}); run `rg models export {name}` again")
    return rep


def verify_gguf(name: str, root) -> dict:
    spec = get_spec(name)
    out = {}
    for f in spec.files:
        p = model_dir(name, root) / f
        if not p.is_file():
            raise ModelMissingError(f"{name}: {f} not found in {p.parent}; run `rg models fetch {name}`")
        with open(p, "rb") as fh:
            if fh.read(4) != b"GGUF":
                raise ModelError(f"{name}: {p} is not a GGUF file (no GGUF magic)")
        out[f] = p.stat().st_size
    return {"gguf_files": out}


def verify(name: str, root: Path | None = None) -> dict:
    spec = get_spec(name)
    rep = {"name": name, **_hash_check(name, root)}
    if spec.kind == "clip":
        rep.update(verify_clip(name, root))
    elif spec.kind == "sam":
        rep.update(verify_sam(name, root))
    else:
        rep.update(verify_gguf(name, root))
    rep["ok"] = True
    return rep
