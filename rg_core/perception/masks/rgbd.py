"""Offline default mask generator: hierarchical, class-agnostic segmentation of an RGB-D view.

No weights. Depth is the strong cue: the dominant support planes are found with RANSAC (open3d)
and removed; the remaining pixels are connected where the surface is continuous, and the
connections are cut at depth jumps, at creases of the surface normal and at colour edges. Three
thresholds give SAM-like levels:

- level 2 "group": cut at depth jumps only (objects that touch stay together) + the support planes,
- level 1 "object": also cut at normal creases and strong colour edges,
- level 0 "part": also cut at weaker colour edges.

Each mask's confidence is its stability: the IoU of its best match when the thresholds are
perturbed (as SAM's stability score). Near-identical masks are de-duplicated (IoU > 0.9).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ...geometry.normals import organised_normals
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
        nrm = organised_normals(pts, valid)
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
        for level, crease, color in zip((2, 1, 0), cfg.normal_crease_deg, cfg.color_edge):
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
