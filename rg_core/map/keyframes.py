"""Keyframes: what the map keeps of a view, and which views it keeps (why a frame becomes a keyframe,
the same view seen again, the keyframe another one covers best). The Mapper applies the decisions."""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from ..config import MapConfig
from ..geometry.conventions import scale_intrinsics
from ..geometry.rotations import pose_distances
from .frames import downscale_depth


@dataclass
class Keyframe:
    """What the map keeps of a keyframe (working resolution); later stages add masks."""

    index: int                 # position in the input stream
    stamp: float
    cam_to_world: np.ndarray   # [4, 4] OpenCV axes
    K: np.ndarray              # [3, 3] at the working resolution
    rgb: torch.Tensor          # [h, w, 3] float32 in [0, 1]
    depth: torch.Tensor        # [h, w] float32 metres, 0 = invalid
    _scaled: dict = field(default_factory=dict, repr=False, compare=False)  # at_scale's cache

    @property
    def size(self) -> tuple[int, int]:
        return self.rgb.shape[1], self.rgb.shape[0]

    def at_scale(self, scale: float) -> "Keyframe":
        """This keyframe with its images resized by `scale` (cached; 1: itself): colour averaged over
        the area, depth with downscale_depth (blocks across an edge invalid), K rescaled."""
        if scale >= 1.0:
            return self
        if scale not in self._scaled:
            w, h = self.size
            sw, sh = max(1, round(w * scale)), max(1, round(h * scale))
            rgb = cv2.resize(self.rgb.numpy(), (sw, sh), interpolation=cv2.INTER_AREA)
            depth = downscale_depth(self.depth.numpy(), sw, sh)
            self._scaled[scale] = Keyframe(self.index, self.stamp, self.cam_to_world, scale_intrinsics(self.K, sw / w, sh / h),
                                           torch.from_numpy(rgb), torch.from_numpy(depth))
        return self._scaled[scale]


def keyframe_reason(keyframes: list[Keyframe], cfg: MapConfig, stamp: float, frac: float,
                    photo: float) -> tuple[str, bool, bool]:
    """Whether a frame at `stamp` is a keyframe, given the share `frac` of its valid depth the map
    does not explain and the map's colour error `photo` there: (reason, keyframe, near_static: one
    only because fewer than kf_min_count keyframes exist and kf_min_interval passed)."""
    if not keyframes:
        return "first frame", True, False
    if frac > cfg.kf_new_fraction:
        return f"{100 * frac:.1f}% of the view is not in the map", True, False
    if photo > cfg.kf_photo_error:
        return f"map renders this view with colour error {photo:.3f}", True, False
    if len(keyframes) < cfg.kf_min_count and stamp - keyframes[-1].stamp >= cfg.kf_min_interval:
        return (f"{len(keyframes)} keyframe(s) < kf_min_count {cfg.kf_min_count}: a keyframe every "
                f"{cfg.kf_min_interval:g} s until then (a near-static camera)"), True, True
    return f"already mapped ({100 * (1 - frac):.1f}% explained, colour error {photo:.3f})", False, False


def changed_fraction(kf: Keyframe, rgb: torch.Tensor, depth: torch.Tensor, colour_tol: float = 0.1,
                     depth_tol: float = 0.03) -> float:
    """How much of a view differs from keyframe `kf`'s images (same working size; else 1): the share
    of pixels whose colour moved by more than colour_tol in a channel, whose depth moved by more
    than max(depth_tol, depth_tol x depth) or that are valid in one and not the other."""
    if tuple(kf.rgb.shape) != tuple(rgb.shape):
        return 1.0
    a, b = kf.depth > 0, depth > 0
    dz = (kf.depth - depth).abs() > torch.clamp(depth_tol * depth, min=depth_tol)
    changed = ((kf.rgb - rgb).abs().amax(-1) > colour_tol) | (a != b) | (a & b & dz)
    return float(changed.float().mean())


def same_view(keyframes: list[Keyframe], kf: Keyframe, revisit: float) -> tuple[int, float, float] | None:
    """The keyframe nearest to kf's pose if within `revisit` (pose_distances, m-equivalent): (its
    position in `keyframes`, the distance, the share of the view changed since, changed_fraction)."""
    d = pose_distances(np.stack([k.cam_to_world for k in keyframes]), kf.cam_to_world)   # [N]
    j = int(np.argmin(d))
    if d[j] > revisit:
        return None
    return j, d[j], changed_fraction(keyframes[j], kf.rgb, kf.depth)


def most_redundant(keyframes: list[Keyframe], window: int, metres_per_radian: float = 0.3) -> int | None:
    """The position of the keyframe whose view another keyframe covers best: the smallest pose
    distance to its nearest other keyframe (translation + metres_per_radian x rotation angle; ties:
    the oldest). The newest `window` keyframes (the optimisation window) and the last one left stay
    (None: none can go)."""
    n_cand = len(keyframes) - min(window, len(keyframes) - 1)
    if len(keyframes) < 2 or n_cand <= 0:
        return None
    poses = np.stack([kf.cam_to_world for kf in keyframes])            # [N, 4, 4]
    best, victim = np.inf, None
    for i in range(n_cand):
        d = pose_distances(poses, poses[i], metres_per_radian)          # [N]
        d[i] = np.inf
        if d.min() < best:
            best, victim = float(d.min()), i
    return victim
