"""ROS message <-> numpy for the node (cv_bridge is not on PyPI). No rclpy here, only message types.

Poses are camera-to-world 4x4 with OpenCV camera axes, which is what a ROS optical frame
(`*_optical_frame`, REP 103) already uses, so poses of optical frames pass through unchanged.
"""
from __future__ import annotations

import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Vector3
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from rg_core.geometry.conventions import check_rigid
from rg_core.geometry.rotations import rot_to_quat
from rg_core.grounding.result import GroundedObject as CoreObject
from rg_core.grounding.result import GroundingResult
from rg_core.io.ros_images import ENCODINGS
from rg_core.io.ros_input import from_time, transform_to_matrix  # noqa: F401 - from_time: the node's stamps
from rg_core.io.ros_images import _unsupported, decode_color, decode_depth
from rg_core.io.ros_images import image_array as _image_array

from .pointcloud import to_pointcloud2

# ----------------------------------------------------------------------------------- time

def to_time(seconds: float) -> Time:
    """Float seconds -> builtin_interfaces/Time (rounded to the nanosecond)."""
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"stamp: expected finite seconds >= 0, got {seconds}")
    sec, nsec = divmod(int(round(seconds * 1e9)), 1_000_000_000)
    if sec >= 2**31:
        raise ValueError(f"stamp: {seconds} s does not fit builtin_interfaces/Time")
    return Time(sec=sec, nanosec=nsec)


def header(frame_id: str = "", stamp: float | Time | None = None) -> Header:
    if stamp is None:
        stamp = Time()
    elif not isinstance(stamp, Time):
        stamp = to_time(float(stamp))
    return Header(frame_id=frame_id, stamp=stamp)


# ---------------------------------------------------------------------------------- images

def image_to_rgb(msg) -> np.ndarray:
    """Colour Image (rgb8, bgr8, rgba8, bgra8, mono8) or CompressedImage (jpeg/png) -> uint8 [H, W, 3] RGB."""
    return decode_color(msg)


def image_to_depth(msg) -> np.ndarray:
    """Depth Image (16UC1 millimetres or 32FC1 metres) or compressedDepth CompressedImage -> float32
    [H, W] metres; 0 = invalid (zero, NaN, inf and negative values all become 0, as the mapper expects)."""
    return decode_depth(msg)


def image_to_mask(msg: Image) -> np.ndarray:
    """mono8 -> uint8 [H, W]."""
    return _image_array(msg, ("mono8",))[..., 0]


def to_image(array: np.ndarray, encoding: str, frame_id: str = "", stamp: float | Time | None = None) -> Image:
    """array [H, W] or [H, W, C] in the channel order of `encoding` -> Image (packed rows, little-endian)."""
    if encoding not in ENCODINGS:
        raise _unsupported(encoding, ENCODINGS)
    dtype, ch = ENCODINGS[encoding]
    arr = np.asarray(array)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] != ch or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"{encoding}: expected a non-empty array [H, W{'' if ch == 1 else f', {ch}'}], "
                         f"got shape {np.asarray(array).shape}")
    if arr.dtype != dtype:
        raise ValueError(f"{encoding}: expected dtype {np.dtype(dtype)}, got {arr.dtype}")
    h, w = arr.shape[:2]
    data = np.ascontiguousarray(arr.astype(np.dtype(dtype).newbyteorder("<"), copy=False))
    return Image(header=header(frame_id, stamp), height=h, width=w, encoding=encoding, is_bigendian=False,
                 step=w * ch * data.itemsize, data=data.tobytes())


def rgb_to_image(rgb: np.ndarray, frame_id: str = "", stamp: float | Time | None = None) -> Image:
    """uint8 [H, W, 3] RGB -> rgb8."""
    return to_image(rgb, "rgb8", frame_id, stamp)


def mask_to_image(mask: np.ndarray, frame_id: str = "", stamp: float | Time | None = None) -> Image:
    """bool or uint8 [H, W] -> mono8 (True -> 255)."""
    mask = np.asarray(mask)
    if mask.dtype == bool:
        mask = mask.astype(np.uint8) * 255
    return to_image(mask, "mono8", frame_id, stamp)


def depth_to_image(depth: np.ndarray, frame_id: str = "", stamp: float | Time | None = None) -> Image:
    """float32 [H, W] metres -> 32FC1."""
    return to_image(np.asarray(depth, dtype=np.float32), "32FC1", frame_id, stamp)


# ----------------------------------------------------------------------------------- poses

def pose_to_matrix(pose: Pose | PoseStamped) -> np.ndarray:
    """Pose (of an optical frame in the map frame) -> cam_to_world [4, 4] float64."""
    return transform_to_matrix(pose.pose if isinstance(pose, PoseStamped) else pose)


def matrix_to_pose(T: np.ndarray) -> Pose:
    """Rigid [4, 4] -> Pose; raises PoseError for anything that is not a rigid transform."""
    T = check_rigid(T, "cam_to_world")
    x, y, z, w = rot_to_quat(T[:3, :3])
    return Pose(position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)))


# ------------------------------------------------------------------------------- grounding

def _vec(v, cls):
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return cls(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def object_to_msg(obj: CoreObject):
    """rg_core GroundedObject -> rg_interfaces/GroundedObject (OBB rotation -> quaternion)."""
    from rg_interfaces.msg import GroundedObject   # built from msg/; imported late so images/poses work without it

    R = np.asarray(obj.obb_rotation, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(R).all():
        raise ValueError("GroundedObject: OBB rotation contains NaN or inf")
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > 1e-2:
        raise ValueError(f"GroundedObject: OBB rotation is not orthonormal (max |R^T R - I| = {err:.3g})")
    if np.linalg.det(R) < 0:   # a reflected frame describes the same box; make it a rotation
        R = R * np.array([1.0, 1.0, -1.0])
    x, y, z, w = rot_to_quat(R)
    return GroundedObject(
        pose=Pose(position=_vec(obj.obb_center, Point), orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))),
        size=_vec(obj.obb_extent, Vector3), gaussian_count=int(len(obj.gaussian_ids)),
        confidence=float(obj.confidence), aabb_min=_vec(obj.aabb_min, Point), aabb_max=_vec(obj.aabb_max, Point))


def answer_fields(result: GroundingResult, frame_id: str, stamp: float | Time | None, res):
    """The fields every answer carries (Ground and Teach responses): success, message, explanation,
    confidence, objects and their Gaussian centres as one xyz+rgb cloud in `frame_id`."""
    res.success, res.message = bool(result.success), str(result.message)
    res.explanation, res.confidence = str(result.explanation), float(result.confidence)
    res.objects = [object_to_msg(o) for o in result.objects]
    if result.objects:
        pts = np.concatenate([np.asarray(o.points, np.float32).reshape(-1, 3) for o in result.objects])
        cols = np.concatenate([np.asarray(o.colors, np.uint8).reshape(-1, 3) for o in result.objects])
    else:
        pts, cols = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    res.cloud = to_pointcloud2(pts, cols, frame_id, header(frame_id, stamp).stamp)
    return res


def result_to_response(result: GroundingResult, frame_id: str, stamp: float | Time | None = None, response=None):
    """GroundingResult -> Ground.Response: objects, their Gaussian centres as one xyz+rgb cloud, timings."""
    from rg_interfaces.srv import Ground

    res = answer_fields(result, frame_id, stamp, response if response is not None else Ground.Response())
    res.target = str(result.target)
    res.stage_names = [str(k) for k in result.timings]
    res.stage_seconds = [float(v) for v in result.timings.values()]
    return res


def graph_to_msg(objs: list, relations: list, up: np.ndarray, frame_id: str, stamp: float | Time | None = None):
    """Scene graph (relations.SceneObject list, graph_relations edges, up [3]) -> rg_interfaces/SceneGraph."""
    from rg_interfaces.msg import SceneGraph, SceneObject, SceneRelation

    out = SceneGraph(header=header(frame_id, stamp), up=_vec(up, Vector3))
    for o in objs:
        g = object_to_msg(o.obj)
        out.objects.append(SceneObject(name=o.name, names=[n for n, _ in o.names],
                                       name_confidences=[float(c) for _, c in o.names], colour=o.colour,
                                       pose=g.pose, size=g.size, aabb_min=g.aabb_min, aabb_max=g.aabb_max,
                                       gaussian_count=g.gaussian_count))
    n = len(objs)
    for i, pred, j, d in relations:
        if not (0 <= i < n and 0 <= j < n):
            raise ValueError(f"SceneGraph: relation ({i}, {pred!r}, {j}) names an object outside 0..{n - 1}")
        out.relations.append(SceneRelation(subject=int(i), predicate=str(pred), object=int(j), distance=float(d)))
    return out
