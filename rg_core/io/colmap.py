"""COLMAP sparse models, binary or text (`sparse/0/{cameras,images,points3D}.{bin,txt}`, also
`sparse/` itself or nerfstudio's `colmap/sparse/0`), read with pycolmap, plus the photos in
`images/`: a photo-only scene (frames without depth) with COLMAP's points3D for initialisation.

Cameras: SIMPLE_PINHOLE and PINHOLE as they are; SIMPLE_RADIAL, RADIAL and OPENCV undistorted with
OpenCV when a frame loads (io/cameras.py). COLMAP's poses are world-to-camera with OpenCV axes;
frames hold camera-to-world. Images are taken in name order (frame index = position); photos of
another size than their camera (a downscaled copy) scale its intrinsics. Every 8th image is a test
view, unless LERF-OVS labels name the test views (io/ovs_labels.py).
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from ..geometry.conventions import PoseError, check_rigid, scale_intrinsics
from .cameras import colmap_camera, pinhole_or_undistorted
from .images import SceneError
from .ovs_labels import find_labels
from .scene import Frame, Intrinsics, Scene, SparsePoints
from .splits import labelled_split

log = logging.getLogger(__name__)
_MODEL_FILES = ("cameras", "images", "points3D")


def _has_model(d: Path) -> bool:
    return all((d / f"{n}.bin").is_file() for n in _MODEL_FILES) or all((d / f"{n}.txt").is_file() for n in _MODEL_FILES)


def sparse_folder(root: str | Path) -> Path | None:
    """The folder of a scene's COLMAP model (sparse/0, sparse, colmap/sparse/0), or None."""
    root = Path(root)
    for d in (root / "sparse" / "0", root / "sparse", root / "colmap" / "sparse" / "0"):
        if _has_model(d):
            return d
    return None


def read_model(sparse: str | Path):
    """A COLMAP model folder -> pycolmap.Reconstruction; SceneError naming what is missing."""
    sparse = Path(sparse)
    if not sparse.is_dir():
        raise SceneError(f"{sparse}: COLMAP sparse folder not found (expected cameras, images and points3D as .bin "
                         "or .txt)")
    if not _has_model(sparse):
        have = sorted(p.name for p in sparse.iterdir())
        raise SceneError(f"{sparse}: expected cameras, images and points3D, all .bin or all .txt; found {have or 'nothing'}")
    try:
        import pycolmap
    except ImportError as exc:
        raise SceneError(f"{sparse}: reading COLMAP models needs pycolmap (pip install pycolmap; requirements.txt)") from exc
    try:
        return pycolmap.Reconstruction(str(sparse))
    except Exception as exc:   # pycolmap raises its own C++ errors for broken files
        raise SceneError(f"{sparse}: not a readable COLMAP model ({exc})") from exc


def model_points(rec, transform: np.ndarray | None = None, source: str = "") -> SparsePoints:
    """points3D of a Reconstruction (optionally moved by a 4x4 new-from-old world transform)."""
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
    if transform is not None:
        T = np.asarray(transform, np.float64)
        xyz = xyz @ T[:3, :3].T + T[:3, 3]
    return SparsePoints(xyz, rgb, source)


def optional_points(sparse: Path | None, transform: np.ndarray | None = None) -> SparsePoints | None:
    """A model's points when `sparse` holds a readable one, else None (logged): for readers whose
    poses come from elsewhere (LLFF, nerfstudio), for which the points are a bonus."""
    if sparse is None:
        return None
    try:
        return model_points(read_model(sparse), transform, str(sparse))
    except SceneError as exc:
        log.warning("%s: no sparse points (%s)", sparse, exc)
        return None


def _image_size(path: Path) -> tuple[int, int]:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SceneError(f"{path}: not a readable image")
    return img.shape[1], img.shape[0]


def model_frames(rec, images: Path, where: str) -> list[Frame]:
    """The registered images of a Reconstruction as frames (name order), photos under `images`."""
    regs = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not regs:
        raise SceneError(f"{where}: the model has no registered image")
    cams: dict[int, tuple] = {}   # camera id -> (Intrinsics, Undistortion | None)
    frames = []
    for pos, im in enumerate(regs):
        path = images / im.name
        if not path.is_file():
            raise SceneError(f"{path}: file not found (image {im.image_id} of {where})")
        if im.camera_id not in cams:
            cam = rec.cameras[im.camera_id]
            K, dist = colmap_camera(cam.model_name, cam.params, cam.width, cam.height, f"{where}: camera {im.camera_id}")
            w, h = _image_size(path)
            if (w, h) != (cam.width, cam.height):   # a downscaled copy of the photos
                K = scale_intrinsics(K, w / cam.width, h / cam.height)
            K, und = pinhole_or_undistorted(K, dist, w, h)
            cams[im.camera_id] = (Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h), und)
        intr, und = cams[im.camera_id]
        w2c = np.eye(4)
        w2c[:3] = np.asarray(im.cam_from_world().matrix(), np.float64)
        try:
            c2w = check_rigid(np.linalg.inv(w2c), f"{where}: image {im.name}")
        except PoseError as exc:
            raise SceneError(str(exc)) from exc
        frames.append(Frame(index=pos, intrinsics=intr, cam_to_world=c2w, image_path=path, depth_path=None,
                            stamp=float(pos), undistort=und))
    return frames


def read_colmap(root: str | Path, test_every: int = 8, images: str = "images", labelled_in_train: bool = True) -> Scene:
    """A folder with a COLMAP sparse model and its photos (`images/`, or another folder of the same
    names) -> a Scene without depth; LERF-OVS labels beside it are read too (ovs_labels)."""
    root = Path(root)
    if not root.is_dir():
        raise SceneError(f"{root}: scene folder not found")
    sparse = sparse_folder(root)
    if sparse is None:
        raise SceneError(f"{root}: no COLMAP sparse model (expected {root / 'sparse' / '0'}/ or {root / 'sparse'}/ with "
                         "cameras, images and points3D .bin or .txt)")
    if not (root / images).is_dir():
        raise SceneError(f"{root / images}: image folder not found (the photos the model {sparse} was made from)")
    rec = read_model(sparse)
    frames = model_frames(rec, root / images, str(sparse))
    labels = find_labels(root, frames)
    train, test = labelled_split(frames, labels, test_every, labelled_in_train)
    return Scene(root=root, train=train, test=test, kind="colmap", labels=labels,
                 points=model_points(rec, source=str(sparse)))
