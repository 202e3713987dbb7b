"""Reader for YCB-Video frames (`0000NN-{color,depth,label}.png` + `-meta.mat`, `classes.txt`):
real photos with per-pixel class labels, object poses and camera poses.

`read_ycb` gives the single views (2D mask and recognition checks); `read_ycb_scene` gives the same
folder as a posed scene with ground truth, so `rg map` and `rg eval` measure on it:
camera poses from each meta.mat's `rotation_translation_matrix` (world -> camera, metres), visible
masks from the label images (object id = the class's 1-based index), object boxes from the labelled
depth. YCB-Video ships no amodal masks, so amodal figures are reported as missing.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.conventions import PoseError, backproject, check_rigid
from .images import SceneError, read_depth, read_mask, read_rgb
from .scene import Frame, Intrinsics, Scene, SceneObject

MIN_OBJECT_PX = 50   # labelled pixels with depth an object needs in a view to count towards its box
EDGE_PX = 3          # label edges are eroded by this much: their depth is often the background's
BOX_PCT = 1.0        # box = [BOX_PCT, 100 - BOX_PCT] percentiles of the points (stray depth left out)


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


def is_ycb(root: str | Path) -> bool:
    root = Path(root)
    return root.is_dir() and (root / "classes.txt").is_file() and any(root.glob("*-meta.mat"))


def _classes(root: Path) -> list[str]:
    cls_file = root / "classes.txt"
    if not cls_file.is_file():
        raise SceneError(f"{cls_file}: file not found")
    return [ycb_class_name(ln) for ln in cls_file.read_text().splitlines() if ln.strip()]


def _meta(root: Path, stem: str, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    import scipy.io

    path = root / f"{stem}-meta.mat"
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    meta = scipy.io.loadmat(str(path))
    missing = [k for k in keys if k not in meta]
    if missing:
        raise SceneError(f"{path}: missing {', '.join(missing)}")
    return {k: np.asarray(meta[k]) for k in keys}


def _stems(root: Path) -> list[str]:
    stems = [p.name[: -len("-color.png")] for p in sorted(root.glob("*-color.png"))]
    if not stems:
        raise SceneError(f"{root}: no *-color.png frames")
    return stems


def read_ycb(root: str | Path) -> tuple[list[str], list[YCBFrame]]:
    """-> (class names, frames)."""
    root = Path(root)
    classes = _classes(root)
    frames = []
    for stem in _stems(root):
        m = _meta(root, stem, ("factor_depth", "intrinsic_matrix", "cls_indexes"))
        frames.append(YCBFrame(stem, read_rgb(root / f"{stem}-color.png"),
                               read_depth(root / f"{stem}-depth.png", float(m["factor_depth"].ravel()[0])),
                               read_mask(root / f"{stem}-label.png"), m["intrinsic_matrix"].astype(np.float64),
                               [int(i) for i in m["cls_indexes"].ravel()]))
    return classes, frames


@dataclass
class YCBSceneFrame(Frame):
    """A YCB-Video view: the label image is the visible-mask id image (ids = 1-based class index);
    no amodal masks (complete_mask_dir stays None)."""

    class_ids: list[int] = field(default_factory=list)


def read_ycb_scene(root: str | Path, test_every: int = 8) -> Scene:
    """A YCB-Video sequence folder as a posed scene; every `test_every`-th frame is a test view."""
    from .queries import default_queries, description_categories

    root = Path(root)
    classes = _classes(root)
    frames: list[YCBSceneFrame] = []
    for pos, stem in enumerate(_stems(root)):
        m = _meta(root, stem, ("factor_depth", "intrinsic_matrix", "cls_indexes", "rotation_translation_matrix"))
        K = m["intrinsic_matrix"].astype(np.float64)
        where = f"{root / f'{stem}-meta.mat'}"
        if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise SceneError(f"{where}: intrinsic_matrix must be 3x3 with positive focal lengths, got {K.tolist()}")
        Rt = m["rotation_translation_matrix"].astype(np.float64)
        if Rt.shape != (3, 4):
            raise SceneError(f"{where}: rotation_translation_matrix must be 3x4 (world -> camera), got {Rt.shape}")
        try:
            w2c = check_rigid(np.vstack([Rt, [0.0, 0.0, 0.0, 1.0]]), f"{where}: rotation_translation_matrix")
        except PoseError as exc:
            raise SceneError(str(exc)) from exc
        ids = [int(i) for i in m["cls_indexes"].ravel()]
        bad = [i for i in ids if not 1 <= i <= len(classes)]
        if bad:
            raise SceneError(f"{where}: cls_indexes {bad} outside classes.txt's 1..{len(classes)}")
        color = root / f"{stem}-color.png"
        rgb = read_rgb(color)
        intr = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], rgb.shape[1], rgb.shape[0])
        frames.append(YCBSceneFrame(index=int(stem) if stem.isdigit() else pos, intrinsics=intr,
                                    cam_to_world=np.linalg.inv(w2c), image_path=color,
                                    depth_path=root / f"{stem}-depth.png",
                                    depth_scale=float(m["factor_depth"].ravel()[0]), stamp=float(pos),
                                    visible_mask_path=root / f"{stem}-label.png", class_ids=ids))
    objects = _objects(frames, classes, description_categories())
    train = [f for k, f in enumerate(frames) if test_every <= 0 or k % test_every != 0]
    test = [f for k, f in enumerate(frames) if test_every > 0 and k % test_every == 0]
    return Scene(root=root, train=train, test=test, objects=objects, queries=default_queries(objects), kind="ycb")


def _objects(frames: list[YCBSceneFrame], classes: list[str], cats: dict[str, str]) -> list[SceneObject]:
    """Each labelled class's world box from its visible, depth-valid pixels over every view."""
    import cv2

    kernel = np.ones((2 * EDGE_PX + 1, 2 * EDGE_PX + 1), np.uint8)
    pts: dict[int, list[np.ndarray]] = {}
    for f in frames:
        label, depth = f.load_visible_mask(), f.load_depth()
        for i in f.class_ids:
            sel = cv2.erode((label == i).astype(np.uint8), kernel).astype(bool) & (depth > 0)
            if sel.sum() < MIN_OBJECT_PX:
                continue
            pts.setdefault(i, []).append(backproject(depth, f.intrinsics.K, f.cam_to_world)[sel])   # [N, 3] world
    out = []
    for i in sorted(pts):
        p = np.concatenate(pts[i])
        name = classes[i - 1]
        lo, hi = np.percentile(p, BOX_PCT, axis=0), np.percentile(p, 100 - BOX_PCT, axis=0)
        out.append(SceneObject(i, name, cats.get(name, "object"), lo.tolist(), hi.tolist()))
    return out
