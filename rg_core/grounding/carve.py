"""Mask votes on a Gaussian group: a Gaussian that a keyframe sees (its depth there agrees with the
sensor's) outside that keyframe's mask of the target is not part of the target; one that several
keyframes see inside it, and none more often outside, is.

The instance field blends features over object borders, so a feature cluster can hold the table
under an object or a neighbour's rim. The 2D masks that chose the target say where it is and is
not; a view in which a Gaussian is hidden (behind the visible surface) or off-image says nothing
about it, so parts occluded from one camera, which an amodal mask needs, survive on the word of
the views that see them. Masks are not dilated where colour and depth agree (synthetic renders): a
thin object's mask grown by a pixel takes in the table beside it. A real RGB-D sensor's colour and
depth images are registered to a pixel or two at best, so there a mask's edge and the depth edge of
its object are apart and the object's side faces and rims fall "outside" its mask: the votes then
grow each mask by the offset measured between the two (`registration_border`): on YCB-Video 0002 at
the map's 320 px, 2 px; on the synthetic scenes, 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.conventions import project


@dataclass
class MaskView:
    K: np.ndarray            # [3, 3] at the mask's size
    cam_to_world: np.ndarray  # [4, 4] OpenCV axes
    depth: np.ndarray        # [h, w] metres, 0 = unknown
    mask: np.ndarray         # [h, w] bool: the target in this view


@dataclass
class MaskVotes:
    inside: np.ndarray     # [N] views that see the point inside the target's mask
    outside: np.ndarray    # [N] views that see it outside
    projected: np.ndarray  # [N] views where it projects into the mask (seen or hidden)
    on_image: np.ndarray   # [N] views where it projects onto the image
    interior: np.ndarray   # [N] bool: in the object (mask_votes)

    def carved(self, min_views: int = 2, silhouette: float = 0.5) -> np.ndarray:
        """bool [N]: not the target. Among points in front of at least `min_views` views: seen
        outside the mask more often than inside; or seen by none of them (no evidence: the mapper
        seeds only what some view saw, so that is a Gaussian sunk under a surface or drifted),
        unless every view puts it in the object's interior (a lemon's middle, behind its own
        surface); or inside fewer than `silhouette` of the masks' silhouettes (what a wider
        surface hides around the object). Points off every image keep their cluster's word."""
        enough = self.on_image >= min_views
        unseen = ((self.inside + self.outside) == 0) & ~self.interior
        return (self.outside > self.inside) | ((unseen | (self.projected < silhouette * self.on_image)) & enough)

    def voted(self, min_votes: int = 2, by_seen: bool = False) -> np.ndarray:
        """bool [N]: seen inside the mask by at least `min_votes` views and outside by fewer.
        `by_seen`: a point fewer views see needs as many as see it (at least one): a face only one
        keyframe sees, which min_votes would keep out however its views vote."""
        need = np.minimum(min_votes, np.maximum(self.inside + self.outside, 1)) if by_seen else min_votes
        return (self.inside >= need) & (self.inside > self.outside)


def depth_edges(depth: np.ndarray, jump_abs: float = 0.03, jump_rel: float = 0.03) -> np.ndarray:
    """bool [h, w]: the near side of each depth discontinuity (the pixel of the pair that is closer
    to the camera: an object's outline, where its mask's boundary should lie): a 4-neighbour with
    valid depth differs by more than max(jump_abs, jump_rel * depth)."""
    d = np.asarray(depth, np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth_edges: depth must be [h, w], got {list(d.shape)}")
    d = np.where(np.isfinite(d), d, 0.0)
    e = np.zeros(d.shape, bool)
    for dy, dx in ((0, 1), (1, 0)):
        a, b = d[: d.shape[0] - dy, : d.shape[1] - dx], d[dy:, dx:]
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > np.maximum(jump_abs, jump_rel * np.minimum(a, b)))
        e[: d.shape[0] - dy, : d.shape[1] - dx] |= jump & (a < b)
        e[dy:, dx:] |= jump & (b < a)
    return e


def mask_depth_offsets(depth: np.ndarray, masks: list[np.ndarray], reach: float = 5.0) -> np.ndarray:
    """Distances (px) from the boundary pixels of each mask [h, w] to the nearest depth edge of the
    same view, for boundary pixels within `reach` px of one (boundaries along no depth edge, such as
    a print on a box, say nothing about registration). Empty when there is none."""
    import cv2

    e = depth_edges(depth)
    if not e.any():
        return np.zeros(0)
    dist = cv2.distanceTransform((~e).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    out = []
    for m in masks:
        m = np.asarray(m).astype(np.uint8)
        if m.shape != e.shape:
            raise ValueError(f"mask_depth_offsets: mask {m.shape} and depth {e.shape} differ")
        boundary = (m - cv2.erode(m, np.ones((3, 3), np.uint8))).astype(bool)
        dd = dist[boundary]
        out.append(dd[dd <= reach])
    return np.concatenate(out) if out else np.zeros(0)


def registration_border(offsets: np.ndarray, max_px: int = 3, min_pixels: int = 50,
                        registered_share: float = 0.15) -> int:
    """Mask growth (px) for the votes from mask-to-depth-edge offsets [n] (mask_depth_offsets).

    Registered colour and depth put a large share of the measured boundary pixels exactly on the
    depth edge: synthetic renders 49-56 % with ground-truth masks, 23-28 % with the offline RGB-D
    masks (their part-level boundaries lie near, not on, depth edges; seeds 11, 12, 701, room 13);
    a real sensor's misregistration puts few there: 6-10 % (YCB-Video 0000 and 0002, either mask
    source). So: 0 when at least `registered_share` of them are on the edge (offset < 0.5 px) or
    fewer than min_pixels were measured; otherwise the median offset, rounded, between 1 and max_px."""
    o = np.asarray(offsets, np.float64).reshape(-1)
    o = o[np.isfinite(o)]
    if len(o) < min_pixels or float(np.mean(o < 0.5)) >= registered_share:
        return 0
    return int(min(max_px, max(1, round(float(np.median(o))))))


SIZE_TOL = 2.0        # a Gaussian reaches the sensed surface within this many of its largest std devs
DEPTH_TOL_ABS = 0.02  # m: a point this near the sensed depth is that surface (mask_votes' default)
INTERIOR_SPREAD = 30.0  # degrees: views this far apart bound what lies inside an object


def dilated(mask: np.ndarray, border_px: int) -> np.ndarray:
    """mask [h, w] -> uint8 [h, w] grown by border_px pixels (a square), as it is when 0."""
    import cv2

    m = mask.astype(np.uint8)
    return cv2.dilate(m, np.ones((2 * border_px + 1,) * 2, np.uint8)) if border_px > 0 else m


def sight(points: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray, depths, tol_size: np.ndarray,
          depth_tol_abs: float = 0.02, depth_tol_rel: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """points [N, 3] world in V cameras (K [V, 3, 3], cam_to_world [V, 4, 4], sensor depths: V
    arrays [h, w]) -> (on [V, N] bool: projects onto the image, seen [V, N] bool: the sensor depth
    there is within max(abs, rel * depth, tol_size [N]) of the point's, rows [V, N], cols [V, N]
    int64: its pixel, -1 off the image). One batched projection: a query asks this of ~30 views."""
    V, N = len(depths), len(points)
    uv, z = project(points, np.asarray(K, np.float64).reshape(V, 3, 3), np.asarray(cam_to_world, np.float64).reshape(V, 4, 4))
    with np.errstate(invalid="ignore"):
        front = (z > 1e-6) & np.isfinite(uv).all(-1)                                   # [V, N]
        pix = np.where(front[..., None], np.floor(np.where(front[..., None], uv, 0.0)), -1).astype(np.int64)
    u, r = pix[..., 0], pix[..., 1]
    on = np.zeros((V, N), bool)
    seen = np.zeros((V, N), bool)
    for v, depth in enumerate(depths):
        h, w = depth.shape
        on[v] = front[v] & (u[v] >= 0) & (u[v] < w) & (r[v] >= 0) & (r[v] < h)
        d = depth[r[v, on[v]], u[v, on[v]]]
        tol = np.maximum(np.maximum(depth_tol_abs, depth_tol_rel * d), tol_size[on[v]])
        seen[v, on[v]] = (d > 0) & (np.abs(z[v, on[v]] - d) <= tol)
    r[~on], u[~on] = -1, -1
    return on, seen, r, u


def mask_votes(points: np.ndarray, views: list[MaskView], sizes: np.ndarray | None = None, border_px: int = 0,
               depth_tol_abs: float = DEPTH_TOL_ABS, depth_tol_rel: float = 0.02, size_tol: float = SIZE_TOL) -> MaskVotes:
    """points [N, 3] world, sizes [N] (largest std dev, m) -> how many views see each point inside
    and outside their mask of the target (masks dilated by `border_px`), in how many views it
    projects into the mask or anywhere on the image, seen or hidden, and whether it lies in the
    object: every view it projects into hides it inside the mask, no deeper behind the surface
    than the mask is wide (its equal-area disc), and their directions to it spread at least
    INTERIOR_SPREAD degrees (one direction cannot tell the object's inside from what it hides).
    A view sees a point when the sensor depth there is within max(abs, rel * depth, size_tol * size)
    of the point's (`sight`): a Gaussian that large reaches the surface (one sunk into the table is the table)."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"mask_votes: points must be [N, 3], got {list(pts.shape)}")
    tol_size = np.zeros(len(pts)) if sizes is None else size_tol * np.asarray(sizes, np.float64).reshape(-1)
    if tol_size.shape != (len(pts),):
        raise ValueError(f"mask_votes: sizes must be [N] = [{len(pts)}], got {list(np.shape(sizes))}")
    inside, outside, projected, on_image, hidden = (np.zeros(len(pts), np.int32) for _ in range(5))
    rays = np.zeros((len(pts), 3))                                                        # [N, 3] summed
    for v in views:
        if v.depth.shape != v.mask.shape:
            raise ValueError(f"mask_votes: depth {v.depth.shape} and mask {v.mask.shape} differ")
    if not views:
        return MaskVotes(inside, outside, projected, on_image, np.zeros(len(pts), bool))
    ons, seens, rs, us = sight(pts, np.stack([v.K for v in views]), np.stack([v.cam_to_world for v in views]),
                               [v.depth for v in views], tol_size, depth_tol_abs, depth_tol_rel)
    for v, on, seen, r, u in zip(views, ons, seens, rs, us):
        m = dilated(v.mask, border_px)
        hit = np.zeros(len(pts), bool)
        hit[on] = m[r[on], u[on]] > 0
        inside += seen & hit
        outside += seen & ~hit
        projected += hit
        on_image += on
        hid = np.flatnonzero(hit & ~seen)
        if len(hid):
            d = v.depth[r[hid], u[hid]]                                                  # [H] the surface there
            width = 2.0 * np.sqrt(m.sum() / np.pi) * d / v.K[0, 0]                      # [H] m, the mask's
            ray = pts[hid] - v.cam_to_world[:3, 3]                                        # [H, 3]
            behind = ray @ v.cam_to_world[:3, 2] - d
            ok = (d > 0) & (behind > 0) & (behind <= width)
            hidden[hid[ok]] += 1
            rays[hid[ok]] += ray[ok] / np.linalg.norm(ray[ok], axis=1, keepdims=True)
    spread = np.linalg.norm(rays, axis=1) <= np.cos(np.radians(INTERIOR_SPREAD / 2)) * np.maximum(hidden, 1)
    return MaskVotes(inside, outside, projected, on_image, (hidden == on_image) & (hidden >= 2) & spread)
