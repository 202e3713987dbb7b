"""OpenCLIP backend ("open_clip"): the paper's image-text model (OpenCLIP ViT-B/16) through the
open_clip package, from a local checkpoint file (no download).

Crops are preprocessed here (bicubic resize to the model's size + its mean/std, in numpy) rather
than with open_clip's torchvision transforms, so numpy crops go straight in; crops from mask_crop are
square, where this equals open_clip's shortest-side resize + centre crop. open_clip needs torchvision.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import torch

from . import CLIP_MEAN, CLIP_STD, Embedder
from ..base import BackendError


class OpenClipEmbedder(Embedder):
    """open_clip.create_model_and_transforms(model_name, pretrained=checkpoint) + its tokenizer.
    `config_path` registers a model config JSON first (its file stem is the model name)."""

    name = "open_clip"

    def __init__(self, checkpoint: str, model_name: str | None = None, config_path: str | None = None,
                 device: str = "cpu", batch: int = 32):
        problems = [f"the '{p}' package is not installed" for p in ("open_clip", "torchvision")
                    if importlib.util.find_spec(p) is None]
        if config_path is not None and not Path(config_path).is_file():
            problems.append(f"model config file not found: {config_path}")
        if not Path(checkpoint).is_file():
            problems.append(f"checkpoint file not found: {checkpoint}")
        if problems:
            raise BackendError("open_clip: " + "; ".join(problems) + " (needs open_clip_torch, a torchvision "
                               "built for the installed torch, and a local checkpoint; 'onnx_clip' runs an "
                               "exported CLIP without torchvision)")
        try:
            import open_clip
        except Exception as e:  # e.g. a torchvision built for another torch fails at import
            raise BackendError(f"open_clip: importing open_clip failed ({type(e).__name__}: {e}); "
                               f"torchvision must be built for torch {torch.__version__}") from e
        if config_path is not None:
            open_clip.add_model_config(config_path)
            model_name = model_name or Path(config_path).stem
        model_name = model_name or "ViT-B-16"
        if open_clip.get_model_config(model_name) is None:
            raise ValueError(f"open_clip: unknown model {model_name!r}; pass config_path or one of "
                             f"open_clip.list_models()")
        model, _, _ = open_clip.create_model_and_transforms(model_name, pretrained=str(checkpoint), device=device)
        self.model = model.eval()
        self.tokenizer = open_clip.get_tokenizer(model_name)
        self.dim = int(open_clip.get_model_config(model_name)["embed_dim"])
        pp = open_clip.get_model_preprocess_cfg(model)
        size = pp.get("size", 224)
        self.size = int(size if isinstance(size, int) else size[0])
        self.mean = np.asarray(pp.get("mean", CLIP_MEAN), np.float32)
        self.std = np.asarray(pp.get("std", CLIP_STD), np.float32)
        self.device, self.batch = torch.device(device), batch

    def preprocess(self, crops: list[np.ndarray]) -> torch.Tensor:  # -> [N, 3, S, S] float32
        self.check_crops(crops)
        x = np.stack([cv2.resize(c, (self.size, self.size), interpolation=cv2.INTER_CUBIC) for c in crops])
        x = (x.astype(np.float32) / 255.0 - self.mean) / self.std
        return torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2)))

    @torch.no_grad()
    def encode_images(self, crops: list[np.ndarray]) -> torch.Tensor:  # -> [N, D] unit rows
        if not crops:
            return torch.zeros(0, self.dim)
        x = self.preprocess(crops)
        out = [self.model.encode_image(x[i:i + self.batch].to(self.device), normalize=True)
               for i in range(0, len(x), self.batch)]
        return torch.cat(out).float().cpu()

    @torch.no_grad()
    def encode_texts(self, texts: list[str]) -> torch.Tensor:  # -> [N, D] unit rows
        if not texts:
            return torch.zeros(0, self.dim)
        tokens = self.tokenizer(list(texts)).to(self.device)  # [N, L] int64
        return self.model.encode_text(tokens, normalize=True).float().cpu()
