"""Reader for YCB-Video frames (`0000NN-{color,depth,label}.png` + `-meta.mat`, `classes.txt`):
single RGB-D views with per-pixel class labels, for 2D mask and recognition checks on real photos."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .images import SceneError, read_depth, read_mask, read_rgb


@dataclass
class YCBFrame:
    name: str
    rgb: np.ndarray       # [H, W, 3] uint8
    depth: np.ndarray     # [H, W] float32 m
    label: np.ndarray     # [H, W] uint8 class ids (1-based into `classes`), 0 background
    K: np.ndarray         # [3, 3]
    class_ids: list[int]  # classes present (from meta.mat)


def ycb_class_name(raw: str) -> str:
    """'006_mustard_bottle' -> 'mustard bottle'."""
    parts = raw.strip().split("_")
    return " ".join(parts[1:] if parts[0].isdigit() else parts)


def read_ycb(root: str | Path) -> tuple[list[str], list[YCBFrame]]:
    """-> (class names, frames)."""
    import scipy.io

    root = Path(root)
    cls_file = root / "classes.txt"
    if not cls_file.is_file():
        raise SceneError(f"{cls_file}: file not found")
    classes = [ycb_class_name(ln) for ln in cls_file.read_text().splitlines() if ln.strip()]
    frames = []
    for color in sorted(root.glob("*-color.png")):
        stem = color.name[: -len("-color.png")]
        meta_path = root / f"{stem}-meta.mat"
        if not meta_path.is_file():
            raise SceneError(f"{meta_path}: file not found")
        meta = scipy.io.loadmat(str(meta_path))
        try:
            factor = float(np.asarray(meta["factor_depth"]).ravel()[0])
            K = np.asarray(meta["intrinsic_matrix"], np.float64)
            ids = [int(i) for i in np.asarray(meta["cls_indexes"]).ravel()]
        except KeyError as exc:
            raise SceneError(f"{meta_path}: missing {exc}") from exc
        frames.append(YCBFrame(stem, read_rgb(color), read_depth(root / f"{stem}-depth.png", factor),
                               read_mask(root / f"{stem}-label.png"), K, ids))
    if not frames:
        raise SceneError(f"{root}: no *-color.png frames")
    return classes, frames
