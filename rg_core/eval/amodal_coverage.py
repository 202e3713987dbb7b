"""How much of each ground-truth amodal mask was ever seen by the training views (BOP scenes).

Amodal mIoU asks the map for the whole object, hidden parts included. With one viewpoint (e.g.
YCB-Video 0002: the camera moves 2-20 mm) the hidden part was never observed, so no map can
reconstruct it from the data; this module says, per object, how much of the amodal mask that is.

Definition (documented in the README): sample `n_points` points uniformly over the object's mesh
surface (area-weighted, seeded). A surface point is *seen* when, in at least one training view,
posed by that view's ground-truth object pose, it
  - projects inside the image onto a pixel of the object's ground-truth visible mask, and
  - is on the camera-facing surface there: its depth is within `tol_m` of the nearest surface
    point of the object in a 3x3-pixel neighbourhood (a z-buffer of the sampled points).
In a test view, an amodal-mask pixel is *covered* when a seen point projects into it (the seen
points' footprint is dilated by one pixel to close gaps between samples). The figure reported is
`unseen_fraction` = 1 - covered / amodal pixels, per test view where the object is visible
(>= min_visible_px, as rg eval counts views) and its mean per object. 0 means every part of the
amodal mask was seen from some training view; 1 - visible/amodal of the test view itself is what
one viewpoint leaves, so with a nearly static camera the two are close.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..io.ply import read_ply_mesh


def surface_points(model: str | Path, n: int = 200_000, seed: int = 0) -> np.ndarray:
    """[n, 3] points (metres, model frame) uniform over a mm mesh's surface (vertices if no faces)."""
    verts, faces = read_ply_mesh(model)
    verts = verts / 1000.0
    if not len(faces):
        return verts
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(faces), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])


def _project(points: np.ndarray, model_to_cam: np.ndarray, K: np.ndarray, W: int, H: int):
    """-> flat pixel index [M], depth [M], index of the kept points [M] (in front, inside the image)."""
    p = points @ model_to_cam[:3, :3].T + model_to_cam[:3, 3]  # [N, 3] camera, OpenCV axes
    z = p[:, 2]
    front = z > 1e-6
    uv = p[front, :2] / z[front, None] * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    x, y = np.floor(uv[:, 0] + 0.5).astype(np.int64), np.floor(uv[:, 1] + 0.5).astype(np.int64)
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    keep = np.nonzero(front)[0][inside]
    return y[inside] * W + x[inside], z[keep], keep


def seen_points(points: np.ndarray, frames: list, obj_id: int, tol_m: float = 0.005) -> np.ndarray:
    """[N] bool: the surface points some training frame (BopFrame) saw (see the module docstring)."""
    seen = np.zeros(len(points), bool)
    for f in frames:
        g = f.pose_of(obj_id)
        if g is None:
            continue
        W, H = f.intrinsics.width, f.intrinsics.height
        pix, z, keep = _project(points, g.model_to_cam, f.intrinsics.K, W, H)
        zbuf = np.full(W * H, np.inf, np.float32)
        np.minimum.at(zbuf, pix, z.astype(np.float32))
        zbuf = cv2.erode(zbuf.reshape(H, W), np.ones((3, 3), np.uint8)).reshape(-1)  # 3x3 minimum
        vis = f.load_object_visible_mask(obj_id).reshape(-1)
        ok = vis[pix] & (z <= zbuf[pix] + tol_m)
        seen[keep[ok]] = True
    return seen


def unseen_fraction(points: np.ndarray, seen: np.ndarray, frame, obj_id: int) -> float | None:
    """Share of `frame`'s amodal mask of `obj_id` that no seen point covers (None: empty mask)."""
    amodal = frame.load_complete_mask(obj_id)
    if not amodal.any():
        return None
    g = frame.pose_of(obj_id)
    W, H = frame.intrinsics.width, frame.intrinsics.height
    pix, _, _ = _project(points[seen], g.model_to_cam, frame.intrinsics.K, W, H)
    cov = np.zeros(W * H, np.uint8)
    cov[pix] = 1
    cov = cv2.dilate(cov.reshape(H, W), np.ones((3, 3), np.uint8)) > 0
    return float((amodal & ~cov).sum() / amodal.sum())


def amodal_coverage(scene, n_points: int = 200_000, min_visible_px: int = 20, tol_m: float = 0.005) -> dict:
    """Per object name: unseen_fraction per test view and its mean, the seen share of the object's
    surface, and (for comparison) 1 - visible/amodal pixels of the test views themselves."""
    out = {}
    for o in scene.objects:
        pts = surface_points(scene.models[o.id], n_points, seed=o.id)
        seen = seen_points(pts, scene.train, o.id, tol_m)
        views, hidden_here = {}, []
        for f in scene.test:
            if f.pose_of(o.id) is None:
                continue
            vis = f.load_object_visible_mask(o.id)
            if vis.sum() < min_visible_px:
                continue
            u = unseen_fraction(pts, seen, f, o.id)
            if u is None:
                continue
            views[f.index] = round(u, 4)
            hidden_here.append(1.0 - float((vis & f.load_complete_mask(o.id)).sum()) / float(f.load_complete_mask(o.id).sum()))
        out[o.name] = {"unseen_fraction": round(float(np.mean(list(views.values()))), 4) if views else None,
                       "per_view": views, "surface_seen": round(float(seen.mean()), 4),
                       "hidden_in_test_view": round(float(np.mean(hidden_here)), 4) if hidden_here else None}
    return out
