"""Camera models of COLMAP and nerfstudio as pinhole intrinsics plus OpenCV distortion, and the
undistortion a Frame applies to its photos when it loads them.

Photos are undistorted at load (OpenCV's remap with maps computed once per camera), never into a
cache folder: nothing is written beside a scene (read-only media work), and the same maps
undistort a benchmark's label masks, which were drawn on the photos as they are on disk. The
pinhole camera of the undistorted image keeps the photo's size and holds valid pixels only
(cv2.getOptimalNewCameraMatrix with alpha 0): no black borders for RGB-only training to fit.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..geometry.conventions import intrinsics_matrix, principal_point_from_corner
from .images import SceneError

# COLMAP's parameter order per model (https://colmap.github.io/cameras.html); the distortion
# coefficients become OpenCV's (k1, k2, p1, p2, k3).
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
SUPPORTED = tuple(COLMAP_MODELS)


@dataclass(eq=False)
class Undistortion:
    """One distorted camera and the pinhole camera its images are resampled to (both OpenCV
    pixel coordinates, one image size). Shared by the frames of that camera."""

    K_src: np.ndarray   # [3, 3] the photo's camera
    dist: np.ndarray    # [5] OpenCV k1, k2, p1, p2, k3
    K: np.ndarray       # [3, 3] the undistorted image's pinhole camera
    width: int
    height: int
    _maps: tuple | None = field(default=None, repr=False)

    def _remap(self, img: np.ndarray, interpolation: int, where) -> np.ndarray:
        h, w = img.shape[:2]
        if (w, h) != (self.width, self.height):
            raise SceneError(f"{where}: image is {w}x{h}, its camera is {self.width}x{self.height}")
        if self._maps is None:
            self._maps = cv2.initUndistortRectifyMap(self.K_src, self.dist, None, self.K,
                                                     (self.width, self.height), cv2.CV_32FC1)
        return cv2.remap(img, *self._maps, interpolation, borderMode=cv2.BORDER_REPLICATE)

    def image(self, img: np.ndarray, where="image") -> np.ndarray:
        """A photo [H, W(, C)] -> its undistorted image (bilinear)."""
        return self._remap(img, cv2.INTER_LINEAR, where)

    def mask(self, mask: np.ndarray, where="mask") -> np.ndarray:
        """A label or binary mask [H, W] drawn on the photo -> the same labels on the undistorted
        image (nearest neighbour: labels stay labels)."""
        m = np.asarray(mask)
        out = self._remap(m.astype(np.uint8) if m.dtype == bool else m, cv2.INTER_NEAREST, where)
        return out.astype(bool) if m.dtype == bool else out

    def points(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates [N, 2] on the photo -> where they land on the undistorted image."""
        pts = np.asarray(uv, np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(pts, self.K_src, self.dist, P=self.K).reshape(-1, 2)


def pinhole_or_undistorted(K: np.ndarray, dist, width: int, height: int) -> tuple[np.ndarray, Undistortion | None]:
    """K [3, 3] and OpenCV distortion coefficients (any length up to 5; None or all zero: a pinhole
    camera) -> (K of the images the frames load, the Undistortion or None)."""
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64).reshape(-1)
    if d.size > 5:
        raise ValueError(f"at most 5 OpenCV distortion coefficients (k1, k2, p1, p2, k3), got {d.size}")
    d = np.concatenate([d, np.zeros(5 - d.size)])
    if not np.any(d):
        return np.asarray(K, np.float64), None
    K_new, _ = cv2.getOptimalNewCameraMatrix(K, d, (width, height), 0.0, (width, height))
    return K_new, Undistortion(np.asarray(K, np.float64), d, K_new, width, height)


def colmap_camera(model: str, params, width: int, height: int, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A COLMAP camera (model name, its parameters, image size) -> (K [3, 3] in OpenCV pixel
    coordinates, OpenCV distortion [5] or None). COLMAP's principal point, like nerfstudio's, has
    the centre of the top-left pixel at (0.5, 0.5). SceneError names an unsupported model and the
    supported ones."""
    names = COLMAP_MODELS.get(model)
    if names is None:
        raise SceneError(f"{where}: camera model {model} is not supported; supported: {', '.join(SUPPORTED)}")
    p = np.asarray(params, np.float64).reshape(-1)
    if p.size != len(names):
        raise SceneError(f"{where}: camera model {model} has {len(names)} parameters ({', '.join(names)}), got {p.size}")
    if not np.all(np.isfinite(p)) or width <= 0 or height <= 0:
        raise SceneError(f"{where}: camera parameters must be finite and the size positive, got {p.tolist()} {width}x{height}")
    v = dict(zip(names, p))
    fx, fy = v.get("fx", v.get("f")), v.get("fy", v.get("f"))
    if fx <= 0 or fy <= 0:
        raise SceneError(f"{where}: focal lengths must be positive, got {fx}, {fy}")
    cx, cy = principal_point_from_corner(v["cx"], v["cy"])
    dist = np.array([v.get("k1", 0.0), v.get("k2", 0.0), v.get("p1", 0.0), v.get("p2", 0.0), 0.0])
    return intrinsics_matrix(fx, fy, cx, cy), (dist if np.any(dist) else None)
