"""Scene data types and the ReasoningGD scene layout (reader and writer).

Layout of a scene folder (the contract benchmarks and outside tools rely on)::

    images/NNNN.png            RGB
    depth/NNNN.png             uint16 depth, units of `depth_scale` per metre (1000: mm), 0 = invalid
    mask_visible/NNNN.png      uint8 instance ids of visible pixels, 0 = background
    mask_complete/NNNN/<id>.png  binary amodal mask of object <id> in view NNNN
    transforms_train.json, transforms_test.json   intrinsics + camera-to-world (NeRF axes)
    objects.json               {"objects": [{"id", "name", "category", "aabb_min", "aabb_max"}]}
    queries.json               [{"object_id", "explicit", "implicit": [...]}]
    points3d.ply               scene point cloud

Frames whose entries have no `depth_file_path` read as frames without depth (depth_path None),
as do the photo-only layouts (colmap.py, nerfstudio.py, llff.py): mapping them needs RGB-only
mapping (issue 63), and Scene.require_depth says so before any work starts.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.conventions import (
    PoseError,
    check_rigid,
    intrinsics_matrix,
    nerf_from_opencv,
    opencv_from_nerf,
    principal_point_from_corner,
    principal_point_to_corner,
    scale_intrinsics,
)
from .cameras import Undistortion
from .images import SceneError, check_depth_unit, read_depth, read_mask, read_rgb

NO_DEPTH = "this scene has no depth images: RGB-only mapping (issue 63) is needed"


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in OpenCV pixel coordinates."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:  # [3, 3]
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera resampled to another image size."""
        K = scale_intrinsics(self.K, width / self.width, height / self.height)
        return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)


@dataclass
class Frame:
    """One posed view (RGB-D, or RGB only when depth_path is None). Images load lazily from disk;
    with `undistort` set they are photos of a distorted camera, undistorted at load, and
    `intrinsics` is the pinhole camera of the undistorted images."""

    index: int
    intrinsics: Intrinsics
    cam_to_world: np.ndarray  # [4, 4] OpenCV axes
    image_path: Path
    depth_path: Path | None = None
    depth_scale: float = 1000.0
    stamp: float = 0.0
    visible_mask_path: Path | None = None
    complete_mask_dir: Path | None = None
    undistort: Undistortion | None = None   # the photos' camera is distorted: undistorted at load
    bounds: tuple[float, float] | None = None  # near, far scene depth (LLFF's poses_bounds), if known

    def load_rgb(self) -> np.ndarray:  # [H, W, 3] uint8
        rgb = read_rgb(self.image_path)
        if self.undistort is not None:
            rgb = self.undistort.image(rgb, self.image_path)
        self._check_size(rgb, self.image_path)
        return rgb

    def load_depth(self) -> np.ndarray:  # [H, W] float32 metres, 0 = invalid
        if self.depth_path is None:
            raise SceneError(f"frame {self.index} ({self.image_path.name}): {NO_DEPTH}")
        depth = read_depth(self.depth_path, self.depth_scale)
        if self.undistort is not None:
            depth = self.undistort.mask(depth, self.depth_path)
        self._check_size(depth, self.depth_path)
        check_depth_unit(depth, str(self.depth_path))
        return depth

    def load_visible_mask(self) -> np.ndarray:  # [H, W] uint8 ids
        if self.visible_mask_path is None:
            raise SceneError(f"frame {self.index}: has no visible mask")
        m = read_mask(self.visible_mask_path)
        if self.undistort is not None:
            m = self.undistort.mask(m, self.visible_mask_path)
        self._check_size(m, self.visible_mask_path)
        return m

    def has_amodal_masks(self) -> bool:
        return self.complete_mask_dir is not None

    def load_complete_mask(self, object_id: int) -> np.ndarray:  # [H, W] bool
        if self.complete_mask_dir is None:
            raise SceneError(f"frame {self.index}: has no amodal masks")
        path = self.complete_mask_dir / f"{object_id}.png"
        m = read_mask(path)
        self._check_size(m, path)
        return m > 127

    def _check_size(self, img: np.ndarray, path: Path) -> None:
        h, w = img.shape[:2]
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise SceneError(
                f"{path}: image is {w}x{h}, expected {self.intrinsics.width}x{self.intrinsics.height}"
            )


@dataclass
class SceneObject:
    id: int
    name: str
    category: str
    aabb_min: list[float]
    aabb_max: list[float]


@dataclass
class Query:
    object_id: int
    explicit: str
    implicit: list[str]


@dataclass
class SparsePoints:
    """A scene's sparse point cloud (COLMAP's points3D, points3d.ply): what RGB-only mapping
    initialises its Gaussians from."""

    xyz: np.ndarray   # [N, 3] float64 world
    rgb: np.ndarray   # [N, 3] uint8
    source: str = ""


@dataclass
class Scene:
    """A posed scene: training and test frames, plus ground truth where the source has it.
    `labels` holds an open-vocabulary benchmark's ground truth (io/ovs_labels.py: LERF-OVS,
    3D-OVS); a benchmark that trains on its labelled views lists them in train and test."""

    root: Path
    train: list[Frame]
    test: list[Frame]
    objects: list[SceneObject] = field(default_factory=list)
    queries: list[Query] = field(default_factory=list)
    kind: str = "reasoninggd"
    labels: object | None = None              # ovs_labels.BenchmarkLabels
    points: SparsePoints | None = None        # read with the poses (COLMAP)
    points_path: Path | None = None           # or a PLY beside them, read by load_points
    world_scale: float = 1.0                  # poses and points were multiplied by it on read (world_scale.py)
    world_rule: str = "metric"                # how that factor was chosen: metric, given, points, bounds, ...

    @property
    def frames(self) -> list[Frame]:
        return sorted({id(f): f for f in self.train + self.test}.values(), key=lambda f: f.index)

    def has_depth(self) -> bool:
        return bool(self.train) and all(f.depth_path is not None for f in self.train)

    def require_depth(self) -> None:
        """SceneError before any mapping starts when a training frame has no depth image."""
        missing = [f for f in self.train if f.depth_path is None]
        if missing:
            raise SceneError(f"{self.root}: {NO_DEPTH} ({len(missing)} of {len(self.train)} training frames have "
                             f"none, e.g. {missing[0].image_path.name}); a map built elsewhere can still be scored "
                             "(rg eval SCENE --map MAP)")

    def load_points(self) -> SparsePoints | None:
        """The sparse points for initialisation: in memory, else the PLY at points_path, else None."""
        if self.points is None and self.points_path is not None and Path(self.points_path).is_file():
            from .ply import read_ply, read_ply_mesh

            try:
                xyz, rgb = read_ply(self.points_path)   # write_ply's own format, with colours
            except SceneError:                          # any other PLY: positions, grey
                xyz, _ = read_ply_mesh(self.points_path)
                rgb = np.full((len(xyz), 3), 128, np.uint8)
            self.points = SparsePoints(np.asarray(xyz, np.float64), rgb, str(self.points_path))
        return self.points



def depth_or_none(frame) -> np.ndarray | None:
    """A frame's depth image [H, W] metres, or None where the frame has none (what the visible mask
    then follows: the render alone)."""
    try:
        return frame.load_depth()
    except SceneError:
        return None


# ---------------------------------------------------------------------------------------------
# ReasoningGD reader / writer


def _load_json(path: Path):
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneError(f"{path}: not valid JSON ({exc})") from exc


def _frames_from_transforms(root: Path, name: str) -> list[Frame]:
    path = root / name
    data = _load_json(path)
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "frames"):
        if key not in data:
            raise SceneError(f"{path}: missing key '{key}'")
    cx, cy = principal_point_from_corner(float(data["cx"]), float(data["cy"]))
    intr = Intrinsics(float(data["fl_x"]), float(data["fl_y"]), cx, cy, int(data["w"]), int(data["h"]))
    if intr.fx <= 0 or intr.fy <= 0 or intr.width <= 0 or intr.height <= 0:
        raise SceneError(f"{path}: focal lengths and image size must be positive, got {intr}")
    depth_scale = float(data.get("depth_scale", 1000.0))
    if depth_scale <= 0:
        raise SceneError(f"{path}: depth_scale must be positive, got {depth_scale}")
    frames = []
    for i, fr in enumerate(data["frames"]):
        where = f"{path}: frames[{i}]"
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise SceneError(f"{where}: needs 'file_path' and 'transform_matrix'")
        try:
            c2w_gl = check_rigid(np.array(fr["transform_matrix"], dtype=np.float64), where)
        except (PoseError, ValueError) as exc:
            raise SceneError(str(exc)) from exc
        img = root / fr["file_path"]
        stem = Path(fr["file_path"]).stem
        try:
            index = int(stem)
        except ValueError as exc:
            raise SceneError(f"{where}: file name '{stem}' is not a frame number NNNN") from exc
        depth = root / fr["depth_file_path"] if fr.get("depth_file_path") else None
        vis = root / "mask_visible" / f"{stem}.png"
        comp = root / "mask_complete" / stem
        frames.append(
            Frame(
                index=index,
                intrinsics=intr,
                cam_to_world=opencv_from_nerf(c2w_gl),
                image_path=img,
                depth_path=depth,
                depth_scale=depth_scale,
                stamp=float(fr.get("stamp", index)),
                visible_mask_path=vis if vis.is_file() else None,
                complete_mask_dir=comp if comp.is_dir() else None,
            )
        )
        for p in (img, depth):
            if p is not None and not p.is_file():
                raise SceneError(f"{p}: file not found (listed in {name})")
    return frames


def read_reasoninggd(root: str | Path) -> Scene:
    """Read a ReasoningGD-layout scene folder; errors name the file and the problem."""
    root = Path(root)
    if not root.is_dir():
        raise SceneError(f"{root}: scene folder not found")
    train = _frames_from_transforms(root, "transforms_train.json")
    test = _frames_from_transforms(root, "transforms_test.json") if (root / "transforms_test.json").is_file() else []
    objects, queries = [], []
    if (root / "objects.json").is_file():
        data = _load_json(root / "objects.json")
        try:
            objects = [SceneObject(**o) for o in data["objects"]]
        except (KeyError, TypeError) as exc:
            raise SceneError(f"{root / 'objects.json'}: bad object entry ({exc})") from exc
    if (root / "queries.json").is_file():
        data = _load_json(root / "queries.json")
        try:
            queries = [Query(**q) for q in data]
        except TypeError as exc:
            raise SceneError(f"{root / 'queries.json'}: bad query entry ({exc})") from exc
    from .ovs_labels import find_labels   # LERF-OVS label files beside it (the scene's own split stays)

    return Scene(root=root, train=train, test=test, objects=objects, queries=queries, kind="reasoninggd",
                 labels=find_labels(root, train + test), points_path=root / "points3d.ply")


def transforms_dict(frames: list[Frame], depth_scale: float = 1000.0) -> dict:
    """The `transforms_*.json` content for frames sharing one camera (NeRF axes, corner pixels)."""
    if not frames:
        raise ValueError("transforms_dict: no frames")
    intr = frames[0].intrinsics
    cx, cy = principal_point_to_corner(intr.cx, intr.cy)
    return {
        "camera_model": "OPENCV",
        "fl_x": intr.fx,
        "fl_y": intr.fy,
        "cx": cx,
        "cy": cy,
        "w": intr.width,
        "h": intr.height,
        "camera_angle_x": float(2.0 * np.arctan(intr.width / (2.0 * intr.fx))),
        "depth_scale": depth_scale,
        "frames": [
            {
                "file_path": f"images/{f.index:04d}.png",
                "depth_file_path": f"depth/{f.index:04d}.png",
                "transform_matrix": [[float(x) for x in row] for row in nerf_from_opencv(f.cam_to_world)],
            }
            for f in frames
        ],
    }


def write_json(path: Path, data) -> None:
    """Deterministic JSON (sorted keys would reorder matrices' dicts only; keep insertion order)."""
    Path(path).write_text(json.dumps(data, indent=1) + "\n")


def write_scene_metadata(root: Path, train: list[Frame], test: list[Frame], objects: list[SceneObject],
                         queries: list[Query], depth_scale: float = 1000.0) -> None:
    """Write transforms, objects.json and queries.json; images are written by the producer."""
    root = Path(root)
    write_json(root / "transforms_train.json", transforms_dict(train, depth_scale))
    if test:
        write_json(root / "transforms_test.json", transforms_dict(test, depth_scale))
    write_json(root / "objects.json", {"objects": [o.__dict__ for o in objects]})
    write_json(root / "queries.json", [q.__dict__ for q in queries])
