"""nerfstudio's data format (`transforms.json` + `images/`), which is also how LERF released its
scenes: a photo-only scene unless frames name a `depth_file_path`.

Read: intrinsics `fl_x, fl_y, cx, cy, w, h` at the top or per frame (a frame's own values win),
`camera_model` (PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV with k1, k2, p1, p2, k3;
distorted photos are undistorted at load, io/cameras.py), frames' `file_path` and
`transform_matrix` (camera-to-world, OpenGL/NeRF axes), optional `depth_file_path` (uint16 mm, as
nerfstudio's default depth unit), `train_filenames` / `test_filenames` (a split nerfstudio names).
Sparse points: `ply_file_path` (nerfstudio writes it in the poses' world), else `colmap/sparse/0`
moved into the poses' world by `applied_transform` (3x4, nerfstudio's new-from-COLMAP world).
Frames are taken in file_path order (nerfstudio's); index = position.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry.conventions import PoseError, check_rigid, intrinsics_matrix, opencv_from_nerf, principal_point_from_corner
from .cameras import COLMAP_MODELS, pinhole_or_undistorted
from .images import SceneError
from .ovs_labels import find_labels
from .scene import Frame, Intrinsics, Scene, _load_json
from .splits import labelled_split, split_every

_CAMERA_KEYS = ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2")


def _camera(spec: dict, where: str, cache: dict) -> tuple[Intrinsics, object]:
    """One frame's camera (top-level values overridden by the frame's) -> Intrinsics and Undistortion."""
    key = tuple(spec.get(k) for k in _CAMERA_KEYS)
    if key in cache:
        return cache[key]
    model = spec.get("camera_model", "OPENCV")
    if model not in COLMAP_MODELS:
        raise SceneError(f"{where}: camera_model {model} is not supported; supported: {', '.join(COLMAP_MODELS)}")
    missing = [k for k in ("fl_x", "fl_y", "cx", "cy", "w", "h") if spec.get(k) is None]
    if missing:
        raise SceneError(f"{where}: missing camera value(s) {', '.join(missing)} (at the top or in the frame)")
    try:
        fx, fy, cx, cy = (float(spec[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
        w, h = int(spec["w"]), int(spec["h"])
        k1, k2, k3, k4, p1, p2 = (float(spec.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    except (TypeError, ValueError) as exc:
        raise SceneError(f"{where}: camera values must be numbers ({exc})") from exc
    if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
        raise SceneError(f"{where}: focal lengths and image size must be positive, got fl_x={fx}, fl_y={fy}, {w}x{h}")
    if k4:
        raise SceneError(f"{where}: k4 belongs to OPENCV_FISHEYE, which is not supported; supported: "
                         f"{', '.join(COLMAP_MODELS)}")
    cx, cy = principal_point_from_corner(cx, cy)
    K, und = pinhole_or_undistorted(intrinsics_matrix(fx, fy, cx, cy), [k1, k2, p1, p2, k3], w, h)
    cache[key] = (Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h), und)
    return cache[key]


def _pose(m, where: str) -> np.ndarray:
    T = np.asarray(m, np.float64)
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    try:
        return opencv_from_nerf(check_rigid(T, where))
    except (PoseError, ValueError) as exc:
        raise SceneError(str(exc)) from exc


def read_nerfstudio(root: str | Path, test_every: int = 8, labelled_in_train: bool = True) -> Scene:
    """A nerfstudio data folder -> a Scene (frames without depth unless the file names depth images)."""
    root = Path(root)
    path = root / "transforms.json"
    data = _load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise SceneError(f"{path}: needs a non-empty 'frames' list")
    top = {k: data[k] for k in _CAMERA_KEYS if k in data}
    cams: dict = {}
    entries = []
    for i, fr in enumerate(data["frames"]):
        where = f"{path}: frames[{i}]"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise SceneError(f"{where}: needs 'file_path' and 'transform_matrix'")
        entries.append((str(fr["file_path"]), i, fr))
    frames = []
    for pos, (fp, i, fr) in enumerate(sorted(entries, key=lambda e: e[0])):
        where = f"{path}: frames[{i}] ({fp})"
        img = root / fp
        if not img.is_file():
            raise SceneError(f"{img}: image not found (file_path of frames[{i}] in {path})")
        intr, und = _camera({**top, **{k: fr[k] for k in _CAMERA_KEYS if k in fr}}, where, cams)
        depth = root / fr["depth_file_path"] if fr.get("depth_file_path") else None
        if depth is not None and not depth.is_file():
            raise SceneError(f"{depth}: depth image not found (depth_file_path of frames[{i}] in {path})")
        frames.append(Frame(index=pos, intrinsics=intr, cam_to_world=_pose(fr["transform_matrix"], where),
                            image_path=img, depth_path=depth, depth_scale=1000.0, stamp=float(pos), undistort=und))
    labels = find_labels(root, frames)
    named = data.get("test_filenames")
    if labels is None and isinstance(named, list) and named:   # nerfstudio's own split
        names = {Path(n).as_posix().lstrip("./") for n in named}
        test = [f for f in frames if f.image_path.relative_to(root).as_posix() in names]
        if len(test) != len(names):
            raise SceneError(f"{path}: test_filenames names {len(names)} images, {len(test)} of them are frames")
        train_names = {Path(n).as_posix().lstrip("./") for n in data.get("train_filenames") or []}
        held = {id(f) for f in test}
        train = ([f for f in frames if f.image_path.relative_to(root).as_posix() in train_names] if train_names
                 else [f for f in frames if id(f) not in held])
    elif labels is None:
        train, test = split_every(frames, test_every)
    else:
        train, test = labelled_split(frames, labels, test_every, labelled_in_train)
    scene = Scene(root=root, train=train, test=test, kind="nerfstudio", labels=labels)
    if data.get("ply_file_path"):
        scene.points_path = root / data["ply_file_path"]
    else:
        _colmap_points(scene, data.get("applied_transform"), path)
    return scene


def _colmap_points(scene: Scene, applied, where: Path) -> None:
    """ns-process-data's colmap/sparse/0 points, in the transforms' world (when pycolmap reads it)."""
    from .colmap import optional_points, sparse_folder

    sparse = scene.root / "colmap" / "sparse" / "0"
    if sparse_folder(scene.root) != sparse:
        return
    T = np.eye(4)
    if applied is not None:
        A = np.asarray(applied, np.float64)
        if A.shape not in ((3, 4), (4, 4)) or not np.isfinite(A).all():
            raise SceneError(f"{where}: applied_transform must be a finite 3x4 matrix, got shape {A.shape}")
        T[:3] = A[:3]
    scene.points = optional_points(sparse, T)
