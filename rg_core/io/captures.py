"""Readers for real RGB-D capture folders and the Open3D `.log` trajectory format.

Capture folders (7-Scenes / tsdf-fusion style) hold `frame-XXXXXX.color.{png,jpg}`,
`frame-XXXXXX.depth.png` (uint16 mm) and `frame-XXXXXX.pose.txt` (4x4 camera-to-world, OpenCV
axes), plus one intrinsics file (`*.K.txt` or `camera-intrinsics.txt`, a 3x3 matrix). A `.log`
trajectory can replace the per-frame pose files.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..geometry.conventions import PoseError, check_rigid
from .images import SceneError
from .scene import Frame, Intrinsics, Scene
from .splits import split_every

_FRAME_RE = re.compile(r"^frame-(\d+)\.color\.(png|jpg)$")


def _read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise SceneError(f"{path}: cannot read a {shape[0]}x{shape[1]} matrix ({exc})") from exc
    if m.shape != shape:
        raise SceneError(f"{path}: expected a {shape[0]}x{shape[1]} matrix, got shape {m.shape}")
    return m


def read_open3d_log(path: str | Path) -> dict[int, np.ndarray]:
    """Open3D `.log` trajectory -> {frame id: 4x4 camera-to-world}. Each entry is a metadata line
    `id id n` followed by four matrix rows."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) % 5:
        raise SceneError(f"{path}: {len(lines)} non-empty lines, expected a multiple of 5 (metadata + 4 rows)")
    poses = {}
    for k in range(0, len(lines), 5):
        try:
            frame_id = int(lines[k][0])
            T = np.array([[float(x) for x in row] for row in lines[k + 1: k + 5]])
            poses[frame_id] = check_rigid(T, f"{path}: entry {k // 5} (frame {frame_id})")
        except (ValueError, IndexError, PoseError) as exc:
            raise SceneError(f"{path}: entry {k // 5}: {exc}") from exc
    return poses


def write_open3d_log(path: str | Path, poses: dict[int, np.ndarray]) -> None:
    """Write {frame id: 4x4 camera-to-world} as an Open3D `.log` trajectory."""
    n = len(poses)
    out = []
    for fid in sorted(poses):
        out.append(f"{fid} {fid} {n}")
        out.extend(" ".join(f"{x:.17g}" for x in row) for row in np.asarray(poses[fid]))
    Path(path).write_text("\n".join(out) + "\n")


def _find_intrinsics(root: Path) -> Path:
    cands = sorted(root.glob("*.K.txt")) + sorted(root.glob("camera-intrinsics.txt"))
    if not cands:
        raise SceneError(f"{root}: no intrinsics file (*.K.txt or camera-intrinsics.txt)")
    return cands[0]


def read_capture(root: str | Path, test_every: int = 8, trajectory: str | Path | None = None) -> Scene:
    """Read a real capture folder. Every `test_every`-th frame (0-based position) is a test view."""
    root = Path(root)
    if not root.is_dir():
        raise SceneError(f"{root}: capture folder not found")
    K = _read_matrix(_find_intrinsics(root), (3, 3))
    entries = sorted((int(m.group(1)), p) for p in root.iterdir() if (m := _FRAME_RE.match(p.name)))
    if not entries:
        raise SceneError(f"{root}: no frame-XXXXXX.color.(png|jpg) files")
    log_poses = read_open3d_log(trajectory) if trajectory is not None else None
    import cv2  # the size of the first colour image sets the intrinsics' image size

    first = cv2.imread(str(entries[0][1]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise SceneError(f"{entries[0][1]}: not a readable image")
    intr = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], first.shape[1], first.shape[0])
    frames = []
    for pos, (fid, color) in enumerate(entries):
        depth = root / f"frame-{fid:06d}.depth.png"
        if not depth.is_file():
            raise SceneError(f"{depth}: file not found (colour frame {color.name} has no depth)")
        if log_poses is not None:
            if fid not in log_poses:
                raise SceneError(f"{trajectory}: no pose for frame {fid}")
            c2w = log_poses[fid]
        else:
            pose_path = root / f"frame-{fid:06d}.pose.txt"
            if not pose_path.is_file():
                raise SceneError(f"{pose_path}: file not found")
            try:
                c2w = check_rigid(_read_matrix(pose_path, (4, 4)), str(pose_path))
            except PoseError as exc:
                raise SceneError(str(exc)) from exc
        frames.append(Frame(index=fid, intrinsics=intr, cam_to_world=c2w, image_path=color,
                            depth_path=depth, depth_scale=1000.0, stamp=float(pos)))
    train, test = split_every(frames, test_every)
    return Scene(root=root, train=train, test=test, kind="capture")


def scene_kind(root: str | Path) -> str | None:
    """Which reader a path is for: "bag", "bop", "reasoninggd", "ycb", "capture", "llff",
    "nerfstudio", "colmap", or None when it is no scene (what read_scene dispatches on; `rg eval DIR`
    tells a scene from a folder of scenes by it)."""
    from .bop import is_bop
    from .colmap import sparse_folder
    from .rosbag import is_bag
    from .ycb import is_ycb

    root = Path(root)
    if is_bag(root):
        return "bag"
    if is_bop(root):
        return "bop"
    if (root / "transforms_train.json").is_file():
        return "reasoninggd"
    if is_ycb(root):
        return "ycb"
    if root.is_dir() and any(_FRAME_RE.match(p.name) for p in root.iterdir()):
        return "capture"
    if (root / "poses_bounds.npy").is_file():   # LLFF, 3D-OVS (its sparse/ made the poses)
        return "llff"
    if (root / "transforms.json").is_file():    # nerfstudio, LERF (colmap/sparse/0 made the poses)
        return "nerfstudio"
    if root.is_dir() and sparse_folder(root) is not None:
        return "colmap"
    return None


def read_scene(root: str | Path, test_every: int = 8, bag_options=None, bop_options=None, photo=None) -> Scene:
    """Read any supported scene: ReasoningGD layout, a real capture folder, a BOP scene folder
    (scene_camera.json + scene_gt.json; `bop_options` a bop.BopOptions, else every `test_every`-th
    image a test view), a YCB-Video sequence folder (classes.txt + NNNNNN-meta.mat), a ROS 2 bag (.mcap, .db3 or a rosbag2 folder; `bag_options` is a
    rosbag.BagOptions, default options when None), or photos with poses and no depth: LLFF /
    3D-OVS (poses_bounds.npy), nerfstudio / LERF (transforms.json), a COLMAP model (sparse/0).
    Photos' worlds defined up to scale are brought to metres here, the one place
    (world_scale.normalise_scale; `photo` a config.PhotoMapConfig for its world_scale and
    world_depth, default auto)."""
    from .world_scale import normalise_scale

    scene = _read_any(root, test_every, bag_options, bop_options)
    if photo is None:
        from ..config import PhotoMapConfig

        photo = PhotoMapConfig()
    return normalise_scale(scene, photo.world_scale, photo.world_depth)


def _read_any(root, test_every, bag_options, bop_options) -> Scene:
    from .bop import BopOptions, read_bop
    from .rosbag import read_bag
    from .scene import read_reasoninggd
    from .ycb import read_ycb_scene

    root = Path(root)
    kind = scene_kind(root)
    if kind == "bag":
        return read_bag(root, bag_options, test_every=test_every)
    if kind == "bop":
        return read_bop(root, bop_options or BopOptions(test_every=test_every))
    if kind == "reasoninggd":
        return read_reasoninggd(root)
    if kind == "ycb":
        return read_ycb_scene(root, test_every=test_every)
    if kind == "capture":
        return read_capture(root, test_every=test_every)
    if kind == "llff":
        from .llff import read_llff

        return read_llff(root, test_every=test_every)
    if kind == "nerfstudio":
        from .nerfstudio import read_nerfstudio

        return read_nerfstudio(root, test_every=test_every)
    if kind == "colmap":
        from .colmap import read_colmap

        return read_colmap(root, test_every=test_every)
    raise SceneError(
        f"{root}: not a scene folder or bag (expected transforms_train.json, frame-XXXXXX.color.png files, "
        "scene_camera.json + scene_gt.json (BOP), classes.txt + *-meta.mat (YCB-Video), a .mcap/.db3 file or a rosbag2 folder with metadata.yaml, "
        "poses_bounds.npy (LLFF), transforms.json (nerfstudio) or a COLMAP model in sparse/0)"
    )
