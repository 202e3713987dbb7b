"""Mask generator interface: image (+ depth, + camera) -> masks with confidence and level.

Backends register by name; configuration picks one. A backend that cannot load says which file
or package it needs.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..base import BackendError, Mask  # noqa: F401 - the mask interface's types


class MaskGenerator:
    name = "base"
    needs_depth = False

    def generate(self, rgb: np.ndarray, depth: np.ndarray | None = None, K: np.ndarray | None = None) -> list[Mask]:
        raise NotImplementedError

    def check_inputs(self, rgb, depth, K) -> None:
        if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"{self.name}: rgb must be uint8 [H, W, 3], got "
                             f"{getattr(rgb, 'dtype', type(rgb))} {getattr(rgb, 'shape', '')}")
        if self.needs_depth:
            if depth is None or K is None:
                raise ValueError(f"{self.name}: needs depth [H, W] (m) and K [3, 3]")
            if depth.shape != rgb.shape[:2]:
                raise ValueError(f"{self.name}: depth {depth.shape} does not match rgb {rgb.shape[:2]}")
            if np.asarray(K).shape != (3, 3):
                raise ValueError(f"{self.name}: K must be [3, 3], got {np.asarray(K).shape}")


_REGISTRY: dict[str, Callable[..., MaskGenerator] | str] = {
    "rgbd": "rg_core.perception.masks.rgbd:RGBDMaskGenerator",
    "sam_onnx": "rg_core.perception.masks.sam:SamOnnxGenerator",
    "sam": "rg_core.perception.masks.sam:SegmentAnythingGenerator",
}


def register(name: str, factory: Callable[..., MaskGenerator] | str) -> None:
    """Add a backend: a factory, or "package.module:attr" imported when first made."""
    _REGISTRY[name] = factory


def make_mask_generator(name: str, **kwargs) -> MaskGenerator:
    from ...util import make_registered

    return make_registered("mask generator", _REGISTRY, name, **kwargs)
