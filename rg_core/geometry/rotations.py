"""Quaternions [x, y, z, w] (the ROS order) <-> rotation matrices, through scipy's Rotation: one
home for the node's messages, the TF buffer and the bag writer."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .conventions import PoseError

QUAT_NORM_TOL = 1e-2   # |norm - 1| above this is a broken quaternion, not rounding


def quat_to_rot(q) -> np.ndarray:
    """Quaternion [x, y, z, w] -> rotation [3, 3] float64 (normalised first)."""
    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def checked_quat_to_rot(q) -> np.ndarray:
    """quat_to_rot for input from outside (messages, files): PoseError for NaN/inf or a norm far
    from 1, which is a broken quaternion rather than rounding."""
    q = np.asarray(q, dtype=np.float64)
    if not np.isfinite(q).all():
        raise PoseError(f"quaternion contains NaN or inf: {q.tolist()}")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > QUAT_NORM_TOL:
        raise PoseError(f"quaternion norm is {n:.4g}, expected 1 (x, y, z, w = {q.tolist()})")
    return quat_to_rot(q / n)


def rot_to_quat(R) -> np.ndarray:
    """Rotation [3, 3] -> unit quaternion [x, y, z, w] with w >= 0. A slightly non-orthonormal
    matrix (a float32 PCA) or a reflection is first replaced by the nearest rotation (SVD)."""
    R = np.asarray(R, dtype=np.float64)
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    q = Rotation.from_matrix(R).as_quat()
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose_distances(poses: np.ndarray, pose: np.ndarray, metres_per_radian: float = 0.3) -> np.ndarray:
    """How far each of poses [N, 4, 4] is from pose [4, 4]: translation (m) + metres_per_radian x
    the relative rotation angle (rad), one number that orders views by overlap. -> [N]."""
    poses = np.asarray(poses, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    ang = (Rotation.from_matrix(pose[:3, :3]).inv() * Rotation.from_matrix(poses[:, :3, :3])).magnitude()
    return np.linalg.norm(poses[:, :3, 3] - pose[:3, 3], axis=1) + metres_per_radian * ang
