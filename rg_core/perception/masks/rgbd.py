"""Offline default mask generator: hierarchical, class-agnostic segmentation of an RGB-D view.

No weights. Depth is the strong cue: the dominant support planes are found with RANSAC (open3d)
and removed; the remaining pixels are connected where the surface is continuous, and the
connections are cut at depth jumps, at creases of the surface normal and at colour edges. Three
thresholds give SAM-like levels:

- level 2 "group": cut at depth jumps only (objects that touch stay together) + the support planes,
- level 1 "object": the part-level segments joined where most of their shared boundary is a smooth,
  flat or convex surface (LCCP-like: Stein et al., CVPR 2014). Touching objects meet in a concave
  valley or a step along the view; a knife's red handle and black blade, or a cup's rim, do not.
  A vote over the whole boundary, not one pixel path, decides, so a leak does not join two objects,
- level 0 "part": also cut at creases and colour edges.

Each mask's confidence is its stability: the IoU of its best match when the thresholds are
perturbed (as SAM's stability score). Near-identical masks are de-duplicated (IoU > 0.9).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..base import Mask
from . import MaskGenerator


@dataclass
class RGBDMaskConfig:
    depth_jump_rel: float = 0.02      # neighbours further apart than this x depth (+ 5 mm) are cut
    normal_crease_deg: tuple[float, float, float] = (180.0, 40.0, 30.0)  # per level 2, 1, 0
    color_edge: tuple[float, float, float] = (1e9, 28.0, 14.0)          # Lab distance, per level 2, 1, 0
    plane_distance: float = 0.008     # RANSAC inlier distance (m), and the most a plane keeps
    plane_sigmas: float = 4.0         # ... at most this x the plane's own residual scale (robust sigma)
    plane_min_distance: float = 0.002  # ... and at least this (m)
    max_planes: int = 2
    min_plane_fraction: float = 0.08  # a plane must hold this fraction of valid pixels
    min_area: float = 0.001           # masks smaller than this fraction of the image are dropped
    max_masks: int = 40
    dedupe_iou: float = 0.9
    min_stability: float = 0.5
    object_merge: bool = True         # level 1 by boundary votes over part segments; False: colour/crease cut
    merge_offsets: tuple[int, ...] = (1, 2, 3)  # pixel offsets across a boundary that vote
    merge_concave: float = 0.1        # a vote is concave below -this (LCCP's (n_a - n_b) . d)
    merge_step: float = 0.8           # ... a step along the view where |n . d| exceeds this
    merge_share: float = 0.5          # segments join where at least this share of votes join ...
    merge_min_votes: int = 6          # ... and at least this many do
    normal_window_m: float = 0.008    # box window (m at the view's median depth; 3-9 px) smoothing the normals
    min_part_area: float = 0.0002     # smaller part segments join their main neighbour first


def _normals(pts: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per-pixel unit normals [H, W, 3] from central differences of the organised point cloud."""
    dx = np.zeros_like(pts)
    dy = np.zeros_like(pts)
    dx[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    dy[1:-1] = pts[2:] - pts[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), 0.0)
    n[~valid] = 0.0
    return n


def _planes(pts: np.ndarray, valid: np.ndarray, cfg: RGBDMaskConfig, rng_seed: int = 0) -> list[np.ndarray]:
    """Boolean masks of the dominant planes (support surfaces)."""
    import open3d as o3d

    out = []
    remaining = valid.copy()
    n_valid = int(valid.sum())
    o3d.utility.random.seed(rng_seed)
    for _ in range(cfg.max_planes):
        idx = np.flatnonzero(remaining)
        if len(idx) < max(500, cfg.min_plane_fraction * n_valid):
            break
        sub = idx[:: max(1, len(idx) // 20000)]
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.reshape(-1, 3)[sub]))
        model, _ = pc.segment_plane(cfg.plane_distance, 3, 200)
        a, b, c, d = model
        dist = np.abs(pts.reshape(-1, 3) @ np.array([a, b, c]) + d).reshape(valid.shape)
        dist, reach = _refit(pts, dist, remaining & (dist < cfg.plane_distance), cfg)
        plane = remaining & (dist < reach)
        if plane.sum() < cfg.min_plane_fraction * n_valid:
            break
        # Keep the plane's largest connected region (a wall and a table can share a plane).
        n_lab, lab = cv2.connectedComponents(plane.astype(np.uint8), connectivity=8)
        if n_lab > 1:
            sizes = np.bincount(lab.ravel())[1:]
            plane = lab == (1 + int(np.argmax(sizes)))
        out.append(plane)
        remaining &= ~plane
    return out


def _refit(pts: np.ndarray, dist: np.ndarray, inliers: np.ndarray, cfg: RGBDMaskConfig) -> tuple[np.ndarray, float]:
    """(distance [H, W] of every pixel to the least-squares plane of the RANSAC inliers, the reach
    within which a pixel joins that plane): plane_sigmas x the inliers' robust residual sigma,
    between plane_min_distance and plane_distance. A clean sensor's table then leaves a fork or a
    knife lying on it (4-15 mm high) to the objects; a noisy sensor's keeps the RANSAC distance.
    Fewer than 3 inliers: RANSAC's own `dist` [H, W] and distance."""
    if int(inliers.sum()) < 3:
        return dist, cfg.plane_distance
    P = pts[inliers]                                                   # [I, 3]
    P = P[:: max(1, len(P) // 20000)]
    c = P.mean(0)
    n = np.linalg.svd(P - c, full_matrices=False)[2][2]               # the least-squares normal
    r = (P - c) @ n
    sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    reach = float(np.clip(cfg.plane_sigmas * sigma, cfg.plane_min_distance, cfg.plane_distance))
    return np.abs((pts - c) @ n), reach


def _smooth_normals(pts: np.ndarray, valid: np.ndarray, win: int) -> np.ndarray:
    """Unit normals [H, W, 3] of the points box-averaged over `win` px, turned to face the camera."""
    w = valid.astype(np.float64)
    den = cv2.boxFilter(w, -1, (win, win), normalize=False)
    sp = cv2.boxFilter(pts * w[..., None], -1, (win, win), normalize=False) / np.maximum(den, 1e-9)[..., None]
    n = _normals(sp, valid & (den > 0.5 * win * win))
    return np.where(((n * pts).sum(-1) > 0)[..., None], -n, n)


def _window_px(metres: float, K: np.ndarray, z: np.ndarray) -> int:
    """An odd window in pixels (3-9) spanning `metres` at the median depth of `z` (3 when empty)."""
    if not len(z):
        return 3
    px = metres * float(K[0, 0]) / max(float(np.median(z)), 1e-6)
    return int(np.clip(2 * np.floor(px / 2) + 1, 3, 9))


def _pairs(lab: np.ndarray, offsets):
    """Yield (k, slices of p, slices of p + k right or down, ok [h, w]) where p and p + k lie in two
    different segments."""
    H, W = lab.shape
    for k in offsets:
        for dy, dx in ((0, k), (k, 0)):
            a, b = (slice(0, H - dy), slice(0, W - dx)), (slice(dy, H), slice(dx, W))
            ok = (lab[a] >= 0) & (lab[b] >= 0) & (lab[a] != lab[b])
            if ok.any():
                yield k, a, b, ok


def _absorb_small(lab: np.ndarray, jumps, min_px: int) -> np.ndarray:
    """Segments under `min_px` join the neighbour that shares most of their uncut 4-edges, if that
    neighbour is larger (ties by id, so no cycles): texture and sensor noise leave such specks."""
    for _ in range(4):
        n = lab.max() + 1
        if n <= 0:
            return lab
        size = np.bincount(lab[lab >= 0], minlength=n)
        a = np.concatenate([lab[:, :-1][~jumps[0]], lab[:-1][~jumps[1]]])
        b = np.concatenate([lab[:, 1:][~jumps[0]], lab[1:][~jumps[1]]])
        m = (a >= 0) & (b >= 0) & (a != b)
        a, b = np.concatenate([a[m], b[m]]), np.concatenate([b[m], a[m]])
        up = (size[a] < min_px) & ((size[b] > size[a]) | ((size[b] == size[a]) & (b > a)))
        if not up.any():
            return lab
        key, votes = np.unique(a[up].astype(np.int64) * n + b[up], return_counts=True)
        ka, kb = key // n, key % n
        order = np.lexsort((-kb, -votes, ka))            # per small segment: most shared edges first
        ka, kb = ka[order], kb[order]
        first = np.r_[True, ka[1:] != ka[:-1]]
        target = np.arange(n)
        target[ka[first]] = kb[first]
        for _ in range(int(np.ceil(np.log2(n + 1))) + 1):   # follow chains to their end
            target = target[target]
        lab = np.where(lab >= 0, target[np.maximum(lab, 0)], -1)
    return lab


def _merge_parts(lab: np.ndarray, pts: np.ndarray, nrm: np.ndarray, z: np.ndarray, cfg: RGBDMaskConfig,
                 concave: float) -> np.ndarray:
    """Object-level labels [H, W]: part segments `lab` joined where their boundary votes join. Each
    pixel pair across a boundary, k px apart, votes join when its depths are continuous, the step
    between them is not along the normals (an occluding edge) and (n_a - n_b) . d > -concave."""
    n = lab.max() + 1
    if n <= 0:
        return lab
    A, B, J = [], [], []
    for k, a, b, ok in _pairs(lab, cfg.merge_offsets):
        za, zb = z[a][ok], z[b][ok]
        cont = np.abs(za - zb) < k * (0.5 * cfg.depth_jump_rel * np.minimum(za, zb) + 0.002)
        na, nb = nrm[a][ok], nrm[b][ok]
        d = pts[a][ok] - pts[b][ok]
        d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
        step = np.maximum(np.abs((na * d).sum(-1)), np.abs((nb * d).sum(-1))) > cfg.merge_step
        J.append(cont & ~step & (((na - nb) * d).sum(-1) > -concave))
        A.append(lab[a][ok]), B.append(lab[b][ok])
    if not A:
        return lab
    a, b, j = np.concatenate(A), np.concatenate(B), np.concatenate(J)
    key, inv, votes = np.unique(np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b), return_inverse=True,
                                return_counts=True)
    joins = np.bincount(inv, j.astype(np.float64))
    ok = (joins >= cfg.merge_share * votes) & (joins >= cfg.merge_min_votes)
    g = coo_matrix((np.ones(int(ok.sum())), (key[ok] // n, key[ok] % n)), shape=(n, n))
    comp = connected_components(g, directed=False)[1]
    return np.where(lab >= 0, comp[np.maximum(lab, 0)], -1)


def _segments(keep: np.ndarray, cut_right: np.ndarray, cut_down: np.ndarray) -> np.ndarray:
    """Connected components of `keep` pixels over uncut 4-neighbour edges -> labels [H, W] (-1 none)."""
    H, W = keep.shape
    ids = np.arange(H * W).reshape(H, W)
    er = keep[:, :-1] & keep[:, 1:] & ~cut_right
    ed = keep[:-1, :] & keep[1:, :] & ~cut_down
    rows = np.concatenate([ids[:, :-1][er], ids[:-1, :][ed]])
    cols = np.concatenate([ids[:, 1:][er], ids[1:, :][ed]])
    g = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(H * W, H * W))
    _, lab = connected_components(g, directed=False)
    lab = lab.reshape(H, W)
    return np.where(keep, lab, -1)


class RGBDMaskGenerator(MaskGenerator):
    """Hierarchical masks from depth + colour (see module docstring)."""

    name = "rgbd"
    needs_depth = True

    def __init__(self, cfg: RGBDMaskConfig | None = None):
        self.cfg = cfg or RGBDMaskConfig()

    def _edges(self, rgb, depth, K):
        valid = np.isfinite(depth) & (depth > 0)
        H, W = depth.shape
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        z = np.where(valid, depth, 0.0).astype(np.float64)
        pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], -1)
        nrm = _normals(pts, valid)
        lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB).astype(np.float64)
        lab = cv2.GaussianBlur(lab, (3, 3), 0)
        jump_r = np.abs(z[:, 1:] - z[:, :-1])
        jump_d = np.abs(z[1:] - z[:-1])
        tol_r = self.cfg.depth_jump_rel * np.minimum(z[:, 1:], z[:, :-1]) + 0.005
        tol_d = self.cfg.depth_jump_rel * np.minimum(z[1:], z[:-1]) + 0.005
        ang_r = np.degrees(np.arccos(np.clip((nrm[:, 1:] * nrm[:, :-1]).sum(-1), -1, 1)))
        ang_d = np.degrees(np.arccos(np.clip((nrm[1:] * nrm[:-1]).sum(-1), -1, 1)))
        col_r = np.linalg.norm(lab[:, 1:] - lab[:, :-1], axis=-1)
        col_d = np.linalg.norm(lab[1:] - lab[:-1], axis=-1)
        return valid, pts, (jump_r > tol_r, jump_d > tol_d), (ang_r, ang_d), (col_r, col_d)

    def _level(self, keep, jumps, angs, cols, crease, color, scale=1.0):
        cut_r = jumps[0] | (angs[0] > crease * scale) | (cols[0] > color * scale)
        cut_d = jumps[1] | (angs[1] > crease * scale) | (cols[1] > color * scale)
        return _segments(keep, cut_r, cut_d)

    def generate(self, rgb: np.ndarray, depth: np.ndarray | None = None, K: np.ndarray | None = None) -> list[Mask]:
        self.check_inputs(rgb, depth, K)
        cfg = self.cfg
        H, W = depth.shape
        valid, pts, jumps, angs, cols = self._edges(rgb, depth, K)
        planes = _planes(pts, valid, cfg)
        keep = valid.copy()
        for p in planes:
            keep &= ~p
        min_px = max(8, int(cfg.min_area * H * W))
        cands: list[Mask] = [Mask(p, 1.0, 2) for p in planes if p.sum() >= min_px]
        if cfg.object_merge:
            parts = _absorb_small(self._level(keep, jumps, angs, cols, cfg.normal_crease_deg[2], cfg.color_edge[2]),
                                  jumps, max(4, int(cfg.min_part_area * H * W)))
            nrm = _smooth_normals(pts, valid, _window_px(cfg.normal_window_m, K, depth[valid]))
            z = np.where(valid, depth, 0.0).astype(np.float64)
        for level, crease, color in zip((2, 1, 0), cfg.normal_crease_deg, cfg.color_edge):
            if level == 1 and cfg.object_merge:
                base = _merge_parts(parts, pts, nrm, z, cfg, cfg.merge_concave)
                alt = _merge_parts(parts, pts, nrm, z, cfg, 0.5 * cfg.merge_concave)   # perturbed: stability
            else:
                base = self._level(keep, jumps, angs, cols, crease, color)
                alt = self._level(keep, jumps, angs, cols, crease, color, scale=0.8)  # perturbed: stability
            alt_ids, alt_counts = np.unique(alt[alt >= 0], return_counts=True)
            alt_size = dict(zip(alt_ids.tolist(), alt_counts.tolist()))
            ids, counts = np.unique(base[base >= 0], return_counts=True)
            for i, c in zip(ids, counts):
                if c < min_px:
                    continue
                m = base == i
                # Best-matching segment of the perturbed segmentation -> IoU = stability.
                sub, sub_counts = np.unique(alt[m & (alt >= 0)], return_counts=True)
                if len(sub) == 0:
                    continue
                j = int(np.argmax(sub_counts))
                inter = int(sub_counts[j])
                stab = inter / (c + alt_size[int(sub[j])] - inter)
                if stab >= cfg.min_stability:
                    cands.append(Mask(m, float(stab), level))
        return dedupe(cands, cfg.dedupe_iou, cfg.max_masks)


def dedupe(masks: list[Mask], iou_thresh: float, max_masks: int) -> list[Mask]:
    """Drop near-identical masks (keep the higher level, then the more confident one) and keep at
    most `max_masks`, most confident first, all levels represented."""
    order = sorted(range(len(masks)), key=lambda i: (-masks[i].level, -masks[i].score))
    kept: list[Mask] = []
    areas = []
    for i in order:
        m = masks[i]
        a = int(m.mask.sum())
        dup = False
        for k, ka in zip(kept, areas):
            inter = int((m.mask & k.mask).sum())
            if inter and inter / (a + ka - inter) > iou_thresh:
                dup = True
                break
        if not dup:
            kept.append(m)
            areas.append(a)
    kept.sort(key=lambda m: -m.score)
    return kept[:max_masks]
