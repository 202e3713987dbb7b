"""ROS message <-> numpy for the node (cv_bridge is not on PyPI). No rclpy here, only message types.

Poses are camera-to-world 4x4 with OpenCV camera axes, which is what a ROS optical frame
(`*_optical_frame`, REP 103) already uses, so poses of optical frames pass through unchanged.
"""
from __future__ import annotations

import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Vector3
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from rg_core.geometry.conventions import PoseError, check_rigid
from rg_core.grounding.result import GroundedObject as CoreObject
from rg_core.grounding.result import GroundingResult
from rg_core.io.ros_images import ENCODINGS
from rg_core.io.ros_images import _unsupported, decode_color, decode_depth
from rg_core.io.ros_images import image_array as _image_array

from .pointcloud import to_pointcloud2

QUAT_NORM_TOL = 1e-2   # |norm - 1| above this is a broken quaternion, not rounding


# ----------------------------------------------------------------------------------- time

def to_time(seconds: float) -> Time:
    """Float seconds -> builtin_interfaces/Time (rounded to the nanosecond)."""
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"stamp: expected finite seconds >= 0, got {seconds}")
    sec, nsec = divmod(int(round(seconds * 1e9)), 1_000_000_000)
    if sec >= 2**31:
        raise ValueError(f"stamp: {seconds} s does not fit builtin_interfaces/Time")
    return Time(sec=sec, nanosec=nsec)


def from_time(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


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


# ------------------------------------------------------------------------------ intrinsics

def camera_info_to_K(msg: CameraInfo) -> tuple[np.ndarray, tuple[int, int]]:
    """CameraInfo -> (K [3, 3] float64 OpenCV pixel coordinates, (width, height))."""
    if msg.width == 0 or msg.height == 0:
        raise ValueError(f"CameraInfo: image size {msg.width}x{msg.height} is empty")
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(K).all():
        raise ValueError("CameraInfo: K contains NaN or inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"CameraInfo: focal lengths must be > 0, got fx={K[0, 0]}, fy={K[1, 1]} "
                         "(an all-zero K means the camera is uncalibrated)")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise ValueError(f"CameraInfo: K is not a pinhole matrix: {K.tolist()}")
    return K, (int(msg.width), int(msg.height))


# ----------------------------------------------------------------------------------- poses

def quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Unit quaternion -> rotation [3, 3]; normalises, rejects NaN and norms far from 1."""
    q = np.array([x, y, z, w], dtype=np.float64)
    if not np.isfinite(q).all():
        raise PoseError(f"quaternion contains NaN or inf: {q.tolist()}")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > QUAT_NORM_TOL:
        raise PoseError(f"quaternion norm is {n:.4g}, expected 1 (x, y, z, w = {q.tolist()})")
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] -> quaternion [x, y, z, w] with w >= 0 (Shepperd's method; nearest rotation first)."""
    R = np.asarray(R, dtype=np.float64)
    U, _, Vt = np.linalg.svd(R)   # project a slightly non-orthonormal matrix (PCA, float32) onto SO(3)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    t = np.trace(R)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose_to_matrix(pose: Pose | PoseStamped) -> np.ndarray:
    """Pose (of an optical frame in the map frame) -> cam_to_world [4, 4] float64."""
    if isinstance(pose, PoseStamped):
        pose = pose.pose
    p, o = pose.position, pose.orientation
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    if not np.isfinite(t).all():
        raise PoseError(f"position contains NaN or inf: {t.tolist()}")
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(o.x, o.y, o.z, o.w)
    T[:3, 3] = t
    return T


def matrix_to_pose(T: np.ndarray) -> Pose:
    """Rigid [4, 4] -> Pose; raises PoseError for anything that is not a rigid transform."""
    T = check_rigid(T, "cam_to_world")
    x, y, z, w = matrix_to_quat(T[:3, :3])
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
    x, y, z, w = matrix_to_quat(R)
    return GroundedObject(
        pose=Pose(position=_vec(obj.obb_center, Point), orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))),
        size=_vec(obj.obb_extent, Vector3), gaussian_count=int(len(obj.gaussian_ids)),
        confidence=float(obj.confidence), aabb_min=_vec(obj.aabb_min, Point), aabb_max=_vec(obj.aabb_max, Point))


def result_to_response(result: GroundingResult, frame_id: str, stamp: float | Time | None = None, response=None):
    """GroundingResult -> Ground.Response: objects, their Gaussian centres as one xyz+rgb cloud, timings."""
    from rg_interfaces.srv import Ground

    res = response if response is not None else Ground.Response()
    res.success, res.message = bool(result.success), str(result.message)
    res.target, res.explanation = str(result.target), str(result.explanation)
    res.confidence = float(result.confidence)
    res.objects = [object_to_msg(o) for o in result.objects]
    if result.objects:
        pts = np.concatenate([np.asarray(o.points, np.float32).reshape(-1, 3) for o in result.objects])
        cols = np.concatenate([np.asarray(o.colors, np.uint8).reshape(-1, 3) for o in result.objects])
    else:
        pts, cols = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    res.cloud = to_pointcloud2(pts, cols, frame_id, header(frame_id, stamp).stamp)
    res.stage_names = [str(k) for k in result.timings]
    res.stage_seconds = [float(v) for v in result.timings.values()]
    return res
