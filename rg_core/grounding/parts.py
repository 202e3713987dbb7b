"""Objects that touch, split at the concave seam between them: the last step of a point answer.

Where the 2D masks join touching objects in every view (YCB-Video 0002: a pudding box, a potted
meat can and a wooden block in one pile), the instance field joins them too. The surface between
two touching convex objects folds inward; an object's own surface does not (Stein et al.,
"Object partitioning using local convexity", CVPR 2014). Each Gaussian gets the surface normal the
keyframes' depth sees at it; over the group's k-nearest-neighbour graph an edge is concave when
its normals turn towards each other, ((n_i - n_j) . (p_i - p_j) < 0), and weighs
exp(-angle / SIGMA), convex edges 1. Normalized cuts (Shi and Malik 2000) bisect the graph while
a cut is cheap (ncut <= MAX_NCUT), leaves MIN_PART Gaussians each side and runs mostly along
concave edges (mean weight <= MAX_SEAM), each Gaussian then going to the side it is bound to more
(polished); the answer is the part holding the point.
"""
from __future__ import annotations

import numpy as np

from ..geometry.normals import depth_normals

NEIGHBOURS = 8       # graph neighbours per Gaussian
SIGMA = 0.3          # rad: a concave edge turning this much weighs 1/e
MAX_NCUT = 0.3       # a cut costlier than this (normalized cut) is inside one object
MIN_PART = 40        # Gaussians each side of a cut at least; smaller pieces stay with their neighbours
MAX_SEAM = 0.5       # the cut's edges weigh this much on average at most: it follows a concave seam
NORMAL_STEP = 4      # px: depth differences over +-this many pixels (of the keyframe's depth)
MEDIAN_PX = 5        # the keyframe's depth median-filtered over this many pixels first
SWEEP = 37           # thresholds tried along the Fiedler vector
FAR = 6.0            # graph edges longer than this x the median edge join nothing (pieces apart)
POLISH_ROUNDS = 10   # polished: rounds of moving nodes to the side they are bound to more


def seen_normals(keyframes, points: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """points [n, 3] (map frame), sizes [n] (m) -> unit normals [n, 3], the mean of those the
    keyframes whose depth sees each point give it (carve.sight); 0 where none sees it."""
    from .carve import sight

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros((len(pts), 3))
    kfs = list(keyframes)
    if not kfs or not len(pts):
        return out
    depths = [kf.depth.numpy() for kf in kfs]
    c2w = np.stack([np.asarray(kf.cam_to_world, np.float64) for kf in kfs])
    Ks = np.stack([np.asarray(kf.K, np.float64) for kf in kfs])
    _, seen, rows, cols = sight(pts, Ks, c2w, depths, 1.5 * np.asarray(sizes, np.float64).reshape(-1))
    for v in np.flatnonzero(seen.any(1)):
        s = seen[v]
        n = depth_normals(depths[v], Ks[v], NORMAL_STEP, MEDIAN_PX, (rows[v, s], cols[v, s]))   # [m, 3] camera
        out[s] += n @ c2w[v, :3, :3].T
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(norm > 1e-6, out / np.maximum(norm, 1e-6), 0.0)


def seam_graph(points: np.ndarray, normals: np.ndarray, k: int | None = None, sigma: float | None = None):
    """Symmetric sparse weights [n, n] over the k-nearest-neighbour graph of points [n, 3] (edges
    up to FAR x the median edge): exp(-angle / sigma) on concave edges, 1 on the rest (where a
    normal is unknown too)."""
    from scipy.sparse import coo_matrix
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    n, sigma = len(pts), SIGMA if sigma is None else sigma
    k = min((NEIGHBOURS if k is None else k) + 1, n)
    dist, nb = cKDTree(pts).query(pts, k=k)                                             # [n, k]
    i, j, dist = np.repeat(np.arange(n), k - 1), nb[:, 1:].reshape(-1), dist[:, 1:].reshape(-1)
    near = dist <= FAR * float(np.median(dist)) + 1e-12
    i, j = i[near], j[near]
    ni, nj = normals[i], normals[j]
    known = (np.abs(ni).sum(1) > 0) & (np.abs(nj).sum(1) > 0)
    angle = np.arccos(np.clip((ni * nj).sum(1), -1.0, 1.0))
    concave = known & (((ni - nj) * (pts[i] - pts[j])).sum(1) < 0)
    w = np.where(concave, np.exp(-angle / sigma), 1.0)
    W = coo_matrix((w, (i, j)), shape=(n, n)).tocsr()
    return W.maximum(W.T)


def _fiedler(W, r: np.ndarray) -> np.ndarray:
    """The eigenvector [m] of the second smallest eigenvalue of the normalized Laplacian
    I - R W R (R = diag(r)): shift-invert Lanczos on the sparse matrix (4x faster than dense at
    900 Gaussians, from a fixed start: the same answer every run), dense when small or unconverged."""
    from scipy.linalg import eigh
    from scipy.sparse import diags, identity
    from scipy.sparse.linalg import ArpackError, eigsh

    m = len(r)
    L = identity(m) - diags(r) @ W @ diags(r)
    if m > 200:
        try:
            w, V = eigsh(L.tocsc(), k=2, sigma=-1e-3, which="LM", v0=np.linspace(1.0, 2.0, m), tol=1e-10)
            return V[:, int(np.argsort(w)[1])]
        except (ArpackError, RuntimeError):
            pass
    return eigh(L.toarray(), subset_by_index=[0, 1], driver="evx")[1][:, 1]


def _bisect(W, min_part: int, max_seam: float) -> tuple[np.ndarray, float] | None:
    """Sparse symmetric weights W [m, m] -> (side [m] bool, its normalized cut) of the cheapest
    sweep cut along the Fiedler vector that leaves min_part each side and whose edges weigh
    max_seam on average at most (a seam), or None."""
    d = np.asarray(W.sum(1)).reshape(-1)                                                # [m]
    if (d <= 0).any():
        return None
    r = 1.0 / np.sqrt(d)
    y = _fiedler(W, r) * r                                                               # [m]
    e = W.tocoo()
    up = e.row < e.col                                                                   # each edge once
    i, j, w = e.row[up], e.col[up], e.data[up]                                           # [E]
    ts = np.unique(np.quantile(y, np.linspace(0.05, 0.95, SWEEP)))                       # [T]
    side = y[None] > ts[:, None]                                                         # [T, m]
    n_in = side.sum(1)
    across = side[:, i] != side[:, j]                                                    # [T, E]
    cut, edges = across @ w, across.sum(1)
    vol = side @ d
    with np.errstate(divide="ignore", invalid="ignore"):
        ncut = cut / vol + cut / (d.sum() - vol)
    ok = (np.minimum(n_in, len(d) - n_in) >= min_part) & (cut <= max_seam * np.maximum(edges, 1))
    if not ok.any():
        return None
    k = int(np.flatnonzero(ok)[np.argmin(ncut[ok])])
    return polished(W, side[k], min_part), float(ncut[k])


def polished(W, side: np.ndarray, min_part: int = 1, rounds: int = POLISH_ROUNDS) -> np.ndarray:
    """side [m] bool of a cut of weights W [m, m] with each node moved to the side it is bound to
    more (over half its edge weight), until none moves (at most `rounds`; never below min_part a
    side). A sweep along the Fiedler vector is a relaxation: near the seam it can leave a node
    cut off from the surface it continues (convex edges to one side, concave ones to the other)."""
    d = np.asarray(W.sum(1)).reshape(-1)                                                # [m]
    side = np.asarray(side, bool).copy()
    for _ in range(rounds):
        there = np.asarray(W @ side.astype(np.float64)).reshape(-1)                     # [m] weight to the True side
        flip = np.where(side, there < d - there, there > d - there)
        new = side ^ flip
        if not flip.any() or min(int(new.sum()), int((~new).sum())) < min_part:
            break
        side = new
    return side


def concave_parts(points: np.ndarray, normals: np.ndarray, min_part: int | None = None,
                  max_ncut: float | None = None, max_seam: float | None = None,
                  focus: int | None = None) -> np.ndarray:
    """points [n, 3], normals [n, 3] (unit, 0 unknown) -> part label [n] (module docstring).
    Pieces the graph does not connect, smaller than min_part, join the part of their nearest point.
    `focus` (an index): only the part holding that point is split further (what part_at needs)."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    min_part, max_ncut, max_seam = (d if x is None else x for x, d in
                                    ((min_part, MIN_PART), (max_ncut, MAX_NCUT), (max_seam, MAX_SEAM)))
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) < 2 * min_part:
        return np.zeros(len(pts), np.int64)
    W = seam_graph(pts, np.asarray(normals, np.float64).reshape(-1, 3))
    _, comp = connected_components(W, directed=False)
    sizes = np.bincount(comp)
    if focus is not None and sizes[comp[focus]] < min_part and (sizes >= min_part).any():   # a crumb: its big neighbour
        big = np.flatnonzero(sizes[comp] >= min_part)
        focus = int(big[cKDTree(pts[big]).query(pts[focus])[1]])
    todo, parts = [np.flatnonzero(comp == c) for c in range(len(sizes))], []
    while todo:
        idx = todo.pop()
        mine = focus is None or focus in idx
        cut = _bisect(W[idx][:, idx], min_part, max_seam) if mine and len(idx) >= 2 * min_part else None
        if cut is not None and cut[1] <= max_ncut:
            todo += [idx[cut[0]], idx[~cut[0]]]
        else:
            parts.append(idx)
    big = [p for p in parts if len(p) >= min_part] or [max(parts, key=len)]
    label = np.full(len(pts), -1, np.int64)
    for c, p in enumerate(big):
        label[p] = c
    small = label < 0
    if small.any():
        label[small] = label[~small][cKDTree(pts[~small]).query(pts[small])[1]]
    return label


def part_at(points: np.ndarray, normals: np.ndarray, point: np.ndarray) -> np.ndarray:
    """bool [n]: the concave_parts part of points [n, 3] holding the one nearest `point` [3]."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(pts):
        return np.zeros(0, bool)
    at = int(np.argmin(np.linalg.norm(pts - np.asarray(point, np.float64), axis=1)))
    label = concave_parts(pts, normals, focus=at)
    return label == label[at]
