"""Axis-aligned and oriented boxes of a Gaussian group (PCA of the hull, as open3d), robust to degenerate groups."""
from __future__ import annotations

import numpy as np


def robust_inliers(points: np.ndarray, k: float = 3.0) -> np.ndarray:
    """[N, 3] -> bool [N]: points within k robust spreads (MAD) of the median in every axis, so a
    few stray Gaussians far from the object do not inflate its box."""
    if len(points) < 8:
        return np.ones(len(points), bool)
    med = np.median(points, 0)
    mad = np.median(np.abs(points - med), 0) * 1.4826
    return (np.abs(points - med) <= k * np.maximum(mad, 1e-3)).all(1)


def connected_to(points: np.ndarray, anchor: np.ndarray | None, link: float,
                 support: np.ndarray | None = None, against: np.ndarray | None = None,
                 also_share: float = 0.25) -> np.ndarray:
    """bool [N]: the points [N, 3] joined to `anchor` [3] by chains of steps of at most `link` (m),
    starting from the point nearest the anchor; None: the largest such component. An object is one
    piece in space: members that only share its instance feature (the table under it, a look-alike
    elsewhere) are left out.
    `support` (bool [N], e.g. seen inside the reference view's mask): when any point has it, the
    component with the most supported points is kept instead of the anchor's. One pixel can lie:
    a thin object's rim in the mask often carries the depth of the surface behind it (colour and
    depth disagree at edges), and the anchor then falls on a few Gaussians of the background.
    `against` (bool [N], seen outside that mask): with support, every other piece with at least
    `also_share` of the kept piece's supported points, and at least twice as many supported as
    against, is kept too. A real sensor leaves gaps in one object (no depth at a mug's rim splits
    its front wall from its inside) that no step of `link` bridges; the table under an object or a
    neighbour is seen outside the mask."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    n = len(pts)
    if n < 2 or not link > 0:
        return np.ones(n, bool)
    tree = cKDTree(pts)
    pairs = tree.query_pairs(link, output_type="ndarray")                     # [E, 2]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else coo_matrix((n, n))
    _, comp = connected_components(graph, directed=False)
    sup = None if support is None else np.asarray(support, bool).reshape(-1)
    if sup is not None and sup.shape != (n,):
        raise ValueError(f"connected_to: support must be [N] = [{n}], got {list(np.shape(support))}")
    if sup is not None and sup.any():
        counts = np.bincount(comp[sup], minlength=int(comp.max()) + 1)                 # [C]
        keep = counts.argmax()
        if against is not None:
            ag = np.asarray(against, bool).reshape(-1)
            if ag.shape != (n,):
                raise ValueError(f"connected_to: against must be [N] = [{n}], got {list(np.shape(against))}")
            out = np.bincount(comp[ag], minlength=len(counts))
            pieces = (counts >= also_share * counts[keep]) & (counts >= 2 * out)
            pieces[keep] = True
            return pieces[comp]
    elif anchor is None:
        keep = np.bincount(comp).argmax()
    else:
        keep = comp[int(tree.query(np.asarray(anchor, np.float64))[1])]
    return comp == keep


def pca_obb(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """open3d's OrientedBoundingBox.create_from_points in numpy/scipy (open3d costs a new process
    seconds to import): PCA of the convex hull's vertices, axes by decreasing variance, the hull's
    extent along them. points [N >= 4, 3] spanning a volume -> (centre [3], R [3, 3], extent [3]).
    tests/test_boxes.py checks it against open3d."""
    from scipy.spatial import ConvexHull

    pts = np.asarray(points, np.float64)
    hull = pts[ConvexHull(pts).vertices]                                          # [H, 3]
    mean = hull.mean(0)
    cov = (hull - mean).T @ (hull - mean) / len(hull)
    evals, R = np.linalg.eigh(cov)                                                # ascending
    R = R[:, np.argsort(-evals, kind="stable")]
    R /= np.linalg.norm(R, axis=0, keepdims=True)
    local = (hull - mean) @ R                                                     # [H, 3] in the box frame
    lo, hi = local.min(0), local.max(0)
    return R @ ((lo + hi) / 2) + mean, R, hi - lo


def group_boxes(points: np.ndarray):
    """points [N, 3] -> (aabb_min [3], aabb_max [3], obb_center [3], obb_rotation [3, 3], obb_extent [3]).
    Fewer than 4 points or coplanar points get an axis-aligned OBB (a PCA box needs volume)."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts) or not np.isfinite(pts).all():
        raise ValueError(f"group_boxes: need finite points [N >= 1, 3], got {pts.shape}")
    lo, hi = pts.min(0), pts.max(0)
    centre, rot, ext = (lo + hi) / 2, np.eye(3), hi - lo
    if len(pts) >= 4 and np.linalg.matrix_rank(pts - pts.mean(0), tol=1e-6) == 3:
        try:
            centre, r, ext = pca_obb(pts)
            if np.linalg.det(r) < 0:  # keep a right-handed frame (same box)
                r = r.copy()
                r[:, 2] *= -1
            rot = r
        except Exception:  # noqa: BLE001 - qhull's QhullError on (near-)degenerate input: keep the AABB box
            pass
    return lo, hi, centre, rot, ext


def box_iou_aabb(a_min, a_max, b_min, b_max) -> float:
    """3D IoU of two axis-aligned boxes."""
    a_min, a_max, b_min, b_max = (np.asarray(v, np.float64) for v in (a_min, a_max, b_min, b_max))
    inter = np.prod(np.clip(np.minimum(a_max, b_max) - np.maximum(a_min, b_min), 0, None))
    va, vb = np.prod(np.clip(a_max - a_min, 0, None)), np.prod(np.clip(b_max - b_min, 0, None))
    union = va + vb - inter
    return float(inter / union) if union > 0 else 0.0
