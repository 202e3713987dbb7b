"""LLFF scenes (`poses_bounds.npy` + `images/`), the layout of 3D-OVS (with `segmentations/`).

`poses_bounds.npy` is [N, 17]: per image (name order) a 3x5 matrix, row-major, whose columns are
the camera-to-world rotation's axes in LLFF's order (down, right, backwards), the camera centre and
(height, width, focal) of the photos COLMAP saw, then the near and far scene depth. The world is
COLMAP's (LLFF only reorders the axes), so `sparse/0` points, when there, are in it too. The
principal point is the image centre. `factor` picks `images_<factor>/` (LLFF's downscaled copies;
without it `images/`, else images_4, _8 or _2) and the focal length is scaled to the photos' size. Every 8th image is a test view, unless 3D-OVS's
segmentations (or LERF-OVS labels) name the labelled views (io/ovs_labels.py).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..geometry.conventions import PoseError, check_rigid, principal_point_from_corner
from .images import SceneError
from .ovs_labels import find_labels
from .scene import Frame, Intrinsics, Scene
from .splits import labelled_split

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def opencv_from_llff(pose: np.ndarray) -> np.ndarray:
    """One LLFF pose [3, 4] (columns down, right, backwards, centre) -> camera-to-world [4, 4],
    OpenCV axes (right, down, forward)."""
    p = np.asarray(pose, np.float64)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = p[:, 1], p[:, 0], -p[:, 2], p[:, 3]
    return T


def read_llff(root: str | Path, test_every: int = 8, factor: int | None = None, labelled_in_train: bool = True) -> Scene:
    """An LLFF / 3D-OVS scene folder -> a Scene without depth (near/far in Frame.bounds)."""
    root = Path(root)
    path = root / "poses_bounds.npy"
    if not path.is_file():
        raise SceneError(f"{path}: file not found (an LLFF scene holds poses_bounds.npy and images/)")
    try:
        pb = np.load(path)
    except (OSError, ValueError) as exc:
        raise SceneError(f"{path}: not a readable .npy array ({exc})") from exc
    if pb.ndim != 2 or pb.shape[1] != 17 or not len(pb) or not np.isfinite(pb).all():
        raise SceneError(f"{path}: expected a finite [N, 17] array (3x5 pose + near, far per image), got shape {pb.shape}")
    folder = root / ("images" if factor is None else f"images_{factor}")
    if factor is None and not folder.is_dir():   # only LLFF's downscaled copies ship
        folder = next((root / f"images_{n}" for n in (4, 8, 2) if (root / f"images_{n}").is_dir()), folder)
    if not folder.is_dir():
        raise SceneError(f"{folder}: image folder not found (images/, or images_N/ with factor N)")
    names = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(names) != len(pb):
        raise SceneError(f"{path}: {len(pb)} poses, but {folder} holds {len(names)} images (one pose per image, name order)")
    first = cv2.imread(str(names[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise SceneError(f"{names[0]}: not a readable image")
    h, w = first.shape[:2]
    poses = pb[:, :15].reshape(-1, 3, 5)   # [N, 3, 5]
    frames = []
    for i, (p, img) in enumerate(zip(poses, names)):
        H, W, f = p[:, 4]
        if H <= 0 or W <= 0 or f <= 0:
            raise SceneError(f"{path}: image {i} ({img.name}): height, width and focal must be positive, got {H}, {W}, {f}")
        cx, cy = principal_point_from_corner(w / 2.0, h / 2.0)
        intr = Intrinsics(f * w / W, f * h / H, cx, cy, w, h)
        try:
            c2w = check_rigid(opencv_from_llff(p[:, :4]), f"{path}: image {i} ({img.name})")
        except PoseError as exc:
            raise SceneError(str(exc)) from exc
        frames.append(Frame(index=i, intrinsics=intr, cam_to_world=c2w, image_path=img, depth_path=None,
                            stamp=float(i), bounds=(float(pb[i, 15]), float(pb[i, 16]))))
    labels = find_labels(root, frames)
    train, test = labelled_split(frames, labels, test_every, labelled_in_train)
    from .colmap import optional_points, sparse_folder

    return Scene(root=root, train=train, test=test, kind="llff", labels=labels,
                 points=optional_points(sparse_folder(root)))
