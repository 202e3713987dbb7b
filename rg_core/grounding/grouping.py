"""Hierarchical grouping: HDBSCAN over per-Gaussian instance features at one physical scale.

The paper clusters every Gaussian. A query needs only the group it lands in, so by default a
subsample is clustered and the remaining Gaussians join their nearest cluster centre when they lie
as close to it as the cluster's own members do (else they stay noise). `rg report`
shows the time saved and the change in mIoU against clustering all Gaussians.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

log = logging.getLogger(__name__)


@dataclass
class Groups:
    labels: np.ndarray       # [M] int64 cluster per row, -1 noise
    centres: torch.Tensor    # [G, Di] unit mean feature per cluster
    clustered: int           # how many Gaussians HDBSCAN saw
    seconds: float
    radius: torch.Tensor | None = None    # [G] cosine distance of a cluster's farthest member to its centre
    features: torch.Tensor | None = None  # [M, Di] the clustered features (unit rows)
    ids: np.ndarray | None = None         # [M] the Gaussian of each row (a region); None: row i is Gaussian i

    def gaussians(self, rows: np.ndarray) -> np.ndarray:
        """Gaussian ids of some rows."""
        return rows if self.ids is None else self.ids[rows]

    def members(self, g: int, grow: bool = True) -> np.ndarray:
        """Gaussians of group g; with `grow`, also any Gaussian (noise included) as close to the
        centre as the group's own farthest member: HDBSCAN leaves the fringe of a group as noise."""
        m = self.labels == g
        if grow and self.features is not None and self.radius is not None:
            d = 1.0 - (self.features @ self.centres[g]).numpy()
            m |= (self.labels == -1) & (d <= float(self.radius[g]) + 1e-6)
        return self.gaussians(np.nonzero(m)[0])

    def ball(self, query: torch.Tensor, radius: float | None = None) -> np.ndarray:
        """Gaussians within `radius` (default: the median cluster radius) of a feature [Di]: the
        group of a query whose feature lies in no cluster (HDBSCAN left the object as noise)."""
        if self.features is None:
            return np.zeros(0, np.int64)
        if radius is None:
            radius = float(self.radius.median()) if self.radius is not None and len(self.radius) else 0.05
        d = 1.0 - (self.features @ torch.nn.functional.normalize(query.float(), dim=-1)).numpy()
        return self.gaussians(np.nonzero(d <= radius)[0])

    def nearest(self, query: torch.Tensor, k: int) -> tuple[np.ndarray, float]:
        """The k Gaussians whose features are most like `query` [Di] (sorted ids) and their mean similarity."""
        d = self.features @ torch.nn.functional.normalize(query.float(), dim=-1)
        top = torch.topk(d, min(k, len(d))).indices.numpy()
        return np.sort(self.gaussians(top)), float(d[top].mean())

    def containing(self, query: torch.Tensor) -> int:
        """The cluster whose radius holds the feature [Di] (the most similar if several), else -1."""
        if not len(self.centres):
            return -1
        q = torch.nn.functional.normalize(query.float(), dim=-1)
        d = 1.0 - self.centres @ q
        inside = d <= self.radius + 1e-6
        if not bool(inside.any()):
            return -1
        return int(torch.where(inside, d, torch.full_like(d, 9.0)).argmin())


def hdbscan_labels(x: np.ndarray, min_cluster_size: int = 10, eps: float = 0.01, method: str = "eom") -> np.ndarray:
    """The paper's HDBSCAN (allow_single_cluster=False; noise stays noise): x [M, Di] -> [M].
    `method` "eom" is scikit-learn's default (the paper's); "leaf" keeps the finest clusters."""
    from sklearn.cluster import HDBSCAN

    if len(x) < max(2, min_cluster_size):
        return np.full(len(x), -1, np.int64)
    x = x.astype(np.float64)
    hd = HDBSCAN(min_cluster_size=min_cluster_size, cluster_selection_epsilon=eps, allow_single_cluster=False,
                 cluster_selection_method=method, copy=True)
    try:
        return hd.fit_predict(x).astype(np.int64)
    except TypeError as e:
        # scikit-learn <= 1.9.1 with NumPy >= 2.4 raises here when a selected cluster lies below eps
        # (scikit-learn issue #33219): cluster without eps, then merge clusters closer than eps.
        if eps <= 0 or "0-dimensional" not in str(e):
            raise
        log.warning("HDBSCAN with cluster_selection_epsilon=%g failed (%s; scikit-learn #33219): clustering "
                    "with epsilon 0 and merging clusters closer than %g", eps, e, eps)
        hd.set_params(cluster_selection_epsilon=0.0)
        return merge_closer_than(x, hd.fit_predict(x).astype(np.int64), eps)


def merge_closer_than(x: np.ndarray, labels: np.ndarray, eps: float) -> np.ndarray:
    """Clusters (labels >= 0) with two points within `eps` of each other become one; noise stays
    noise. x [M, D], labels [M] -> [M], clusters renumbered 0..G-1."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    inside = np.nonzero(labels >= 0)[0]
    if not len(inside):
        return labels.copy()
    pairs = cKDTree(x[inside]).query_pairs(eps, output_type="ndarray")          # [P, 2]
    a, b = labels[inside[pairs[:, 0]]], labels[inside[pairs[:, 1]]]
    G = int(labels.max()) + 1
    _, comp = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(G, G)), directed=False)
    _, renum = np.unique(comp, return_inverse=True)
    out = np.full(len(labels), -1, np.int64)
    out[inside] = renum.reshape(-1)[labels[inside]]
    return out


def cluster_instances(features: torch.Tensor, max_points: int = 2000, min_cluster_size: int = 10,
                      eps: float = 0.01, assign_quantile: float = 1.0, seed: int = 0, method: str = "eom") -> Groups:
    """features [N, Di] (unit rows) -> Groups. max_points <= 0 clusters everything (the paper)."""
    import time

    t0 = time.perf_counter()
    if features.ndim != 2:
        raise ValueError(f"cluster_instances: features must be [N, Di], got {list(features.shape)}")
    f = torch.nn.functional.normalize(torch.nan_to_num(features.float()), dim=-1, eps=1e-8)
    N = f.shape[0]
    if max_points <= 0 or N <= max_points:
        idx = np.arange(N)
    else:
        idx = np.sort(np.random.default_rng(seed).choice(N, max_points, replace=False))
    sub = hdbscan_labels(f[idx].numpy(), min_cluster_size, eps, method)
    labels = np.full(N, -1, np.int64)
    labels[idx] = sub
    G = int(sub.max()) + 1 if len(sub) else 0
    if G == 0:
        return Groups(labels, torch.zeros(0, f.shape[1]), len(idx), time.perf_counter() - t0, torch.zeros(0), f)
    sub_t = torch.from_numpy(sub)
    fi = f[torch.from_numpy(idx)]
    centres = torch.zeros(G, f.shape[1]).index_add_(0, sub_t.clamp(min=0), fi * (sub_t >= 0)[:, None].float())
    centres = torch.nn.functional.normalize(centres, dim=-1, eps=1e-8)
    # Radius per cluster: how far its own members lie from its centre.
    member = sub_t >= 0
    d_own = 1.0 - (fi[member] * centres[sub_t[member]]).sum(-1)
    radius = torch.zeros(G)
    for g in range(G):
        dg = d_own[sub_t[member] == g]
        radius[g] = torch.quantile(dg, assign_quantile) if len(dg) else 0.0
    if len(idx) < N:
        left = np.ones(N, bool)
        left[idx] = False
        rest = np.flatnonzero(left)                           # = setdiff1d(arange(N), idx), without its sort
        sim = f[torch.from_numpy(rest)] @ centres.T           # [R, G]
        best, arg = sim.max(-1)
        ok = (1.0 - best) <= radius[arg] + 1e-6
        labels[rest] = np.where(ok.numpy(), arg.numpy(), -1)
    return Groups(labels, centres, len(idx), time.perf_counter() - t0, radius, f)
