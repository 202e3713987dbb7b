"""The one module that owns camera and pose conventions.

Inside the library every pose is a 4x4 camera-to-world matrix with **OpenCV camera axes**
(x right, y down, z forward) and every intrinsics matrix uses OpenCV pixel coordinates (the centre
of the top-left pixel is (0, 0)). Everything else is converted at the edges, here:

- NeRF/Blender/nerfstudio camera axes (x right, y up, z backward), as in `transforms_*.json`;
  their principal point is in pixel-corner coordinates (centre of the top-left pixel is (0.5, 0.5)).
- ROS: the optical frame (`*_optical_frame`, REP 103) has OpenCV axes; the body frame of a camera
  link is x forward, y left, z up.
"""
from __future__ import annotations

import numpy as np

from .points import facing_plane

# Flip between OpenCV camera axes and NeRF/Blender camera axes (its own inverse).
CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])
# Rotation taking a vector in the ROS optical frame to the ROS body frame (x fwd, y left, z up).
BODY_FROM_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


class PoseError(ValueError):
    """A matrix that should be a rigid transform is not one."""


def check_rigid(T: np.ndarray, what: str = "pose", tol: float = 1e-3) -> np.ndarray:
    """Return `T` as float64 [4, 4] if it is a finite rigid transform, else raise PoseError."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise PoseError(f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise PoseError(f"{what}: contains NaN or inf")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise PoseError(f"{what}: last row is {T[3].tolist()}, expected [0, 0, 0, 1]")
    R = T[:3, :3]
    ortho_err = float(np.abs(R.T @ R - np.eye(3)).max())
    if ortho_err > tol:
        raise PoseError(f"{what}: rotation is not orthonormal (max |R^T R - I| = {ortho_err:.3g})")
    det = float(np.linalg.det(R))
    if det < 0:
        raise PoseError(f"{what}: rotation is a reflection (det = {det:.3f}), expected det = +1")
    return T


def opencv_from_nerf(c2w_nerf: np.ndarray) -> np.ndarray:
    """Camera-to-world with NeRF/Blender axes -> camera-to-world with OpenCV axes."""
    return np.asarray(c2w_nerf, dtype=np.float64) @ CV_FROM_GL


def nerf_from_opencv(c2w_cv: np.ndarray) -> np.ndarray:
    """Camera-to-world with OpenCV axes -> camera-to-world with NeRF/Blender axes."""
    return np.asarray(c2w_cv, dtype=np.float64) @ CV_FROM_GL


def optical_from_body(c2w_body: np.ndarray) -> np.ndarray:
    """ROS camera body frame pose (x fwd, y left, z up) -> optical frame pose (OpenCV axes)."""
    return np.asarray(c2w_body, dtype=np.float64) @ BODY_FROM_OPTICAL


def body_from_optical(c2w_optical: np.ndarray) -> np.ndarray:
    """ROS optical frame pose -> camera body frame pose."""
    return np.asarray(c2w_optical, dtype=np.float64) @ BODY_FROM_OPTICAL.T


def principal_point_from_corner(cx: float, cy: float) -> tuple[float, float]:
    """nerfstudio/Blender principal point (pixel-corner origin) -> OpenCV (pixel-centre origin)."""
    return cx - 0.5, cy - 0.5


def principal_point_to_corner(cx: float, cy: float) -> tuple[float, float]:
    """OpenCV principal point -> nerfstudio/Blender principal point."""
    return cx + 0.5, cy + 0.5


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 pinhole matrix K (OpenCV pixel coordinates)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for the same camera after resizing the image by (sx, sy) (pixel-centre coordinates)."""
    K = np.asarray(K, dtype=np.float64).copy()
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world (OpenCV axes) for a camera at `eye` looking at `target`, world `up`."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking straight along `up`: any x works
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def up_direction(cam_to_worlds: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """World "up" [3] (unit) from camera poses [N, 4, 4] (OpenCV axes), for maps without gravity.

    Cameras held by people and robots rarely roll, so their x axes lie in the horizontal plane: up
    is the direction most orthogonal to all of them (the smallest eigenvector of sum x x^T), signed
    like the cameras' mean up (-y). When the x axes span one direction only (one viewing direction),
    the poses leave the cameras' pitch open: the normal of the largest plane of `points` [M, 3]
    (the floor or table) within 45 degrees of the mean -y with its x component removed, else that."""
    T = np.asarray(cam_to_worlds, np.float64).reshape(-1, 4, 4)
    if not len(T) or not np.isfinite(T).all():
        raise ValueError(f"up_direction needs finite camera poses [N, 4, 4], got {np.shape(cam_to_worlds)}")
    xs, up0 = T[:, :3, 0], -T[:, :3, 1].mean(0)
    w, v = np.linalg.eigh(xs.T @ xs / len(xs))   # ascending eigenvalues
    if w[1] > 0.05 * w[2]:                          # the x axes span the horizontal plane
        up = v[:, 0]
    else:
        up = up0 - (up0 @ v[:, 2]) * v[:, 2]
    n = np.linalg.norm(up)
    if n < 1e-9:
        raise ValueError("up_direction: camera poses give no up direction")
    up = up / n
    up = up if up @ up0 >= 0 else -up
    if w[1] <= 0.05 * w[2] and points is not None and len(points) >= 3:
        plane = facing_plane(points, up)
        up = up if plane is None else plane
    return up


def pixels_to_points(u, v, z, K: np.ndarray, c2w: np.ndarray | None = None) -> np.ndarray:
    """Pixel coordinates u, v and depth z (m), arrays of one shape [...] -> points [..., 3] (camera
    frame, or world if c2w given)."""
    u, v, z = (np.asarray(a, np.float64) for a in (u, v, z))
    pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=-1)
    if c2w is not None:
        pts = pts @ c2w[:3, :3].T + c2w[:3, 3]
    return pts


def backproject(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray | None = None) -> np.ndarray:
    """Depth map [H, W] in metres -> points [H, W, 3] (camera frame, or world if c2w given)."""
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    return pixels_to_points(u, v, depth, K, c2w)


def project(points_world: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] -> (pixel coords [..., N, 2] OpenCV, depth [..., N]) in the cameras
    `c2w` [..., 4, 4] with intrinsics K [..., 3, 3] (one camera or a batch of them)."""
    w2c = np.linalg.inv(c2w)
    pc = points_world @ np.swapaxes(w2c[..., :3, :3], -1, -2) + w2c[..., None, :3, 3]   # [..., N, 3]
    z = pc[..., 2]
    f, c = K[..., None, [0, 1], [0, 1]], K[..., None, [0, 1], [2, 2]]                  # [..., 1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = f * pc[..., :2] / z[..., None] + c
    return uv, z


def in_image(uv: np.ndarray, z: np.ndarray, width: int, height: int, near: float = 0.0) -> np.ndarray:
    """Which projections (`project`'s uv [N, 2], z [N]) land on a width x height image in front of
    the `near` plane: bool [N]. Pixel i covers [i - 0.5, i + 0.5) (OpenCV centres), so
    np.round(uv) of the kept ones indexes the image; NaN/inf projections are out."""
    with np.errstate(invalid="ignore"):
        return ((z > near) & (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5)
                & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5))


def depth_resolution(K: np.ndarray, cam_to_worlds: np.ndarray, depth: float) -> float:
    """Metres of depth that one pixel of disparity spans at `depth` (m) between the two cameras
    (K [V, 3, 3], cam_to_world [V, 4, 4]) farthest apart: depth^2 / (f B), f the median focal length
    (px), B that baseline; at most `depth` (one camera, or none apart: depth is not resolved). How
    well photos place a surface in depth: 2 mm for views around a table top, ~0.2 m for cameras
    within 11 mm of each other at 1.1 m (YCB-Video 0002)."""
    from scipy.spatial.distance import pdist

    K, c2w = np.asarray(K, np.float64).reshape(-1, 3, 3), np.asarray(cam_to_worlds, np.float64).reshape(-1, 4, 4)
    if not depth > 0:
        return 0.0
    f = float(np.median((K[:, 0, 0] + K[:, 1, 1]) / 2))
    base = float(pdist(c2w[:, :3, 3]).max()) if len(c2w) > 1 else 0.0
    return float(min(depth, depth * depth / (f * base))) if f * base > 0 else float(depth)
