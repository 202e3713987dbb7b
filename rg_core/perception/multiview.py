"""Multi-view consistency of mask embeddings, as the paper does: the same object seen from several
keyframes gets one embedding, the area-weighted mean of its per-view embeddings.

Masks are associated through the 3D map: each mask collects the Gaussians that dominate its pixels
(the rasterizer's `ids`), as the voxels (one map spacing wide) that hold them; two masks from
different keyframes are the same object when those voxel sets overlap (Jaccard >= min_jaccard) and
their physical scales agree within a factor; links are merged best first, never putting two masks
of one keyframe in one object. Voxels, not Gaussian ids: a keyframe's densification
adds small Gaussians that dominate its own view, on the same surface the other views see.
"""
from __future__ import annotations

import numpy as np
import torch


def mask_gaussians(mapper, sset, voxel_spacings: float = 1.0) -> tuple[list[tuple[int, int]], "object"]:
    """Incidence of masks and the voxels of the Gaussians that dominate them: rows (keyframe index,
    mask index), CSR matrix [masks, V]; `voxel_spacings` <= 0 uses the Gaussians themselves."""
    from scipy.sparse import csr_matrix

    from ..geometry.points import map_spacing

    kfs = {kf.index: kf for kf in mapper.keyframes}
    rows, cols, keys = [], [], []
    means = mapper.gaussians.means.detach().numpy()
    N = len(means)
    cell = np.arange(N)
    if voxel_spacings > 0 and N > 1:
        vox = max(voxel_spacings * map_spacing(means), 1e-6)
        _, cell = np.unique(np.floor(means / vox).astype(np.int64), axis=0, return_inverse=True)
        cell = cell.reshape(-1)
    V = int(cell.max()) + 1 if N else 1
    for k in sorted(sset.by_keyframe):
        sup = sset.by_keyframe[k]
        if k not in kfs or not len(sup.masks):
            continue
        kf = kfs[k]
        w, h = kf.size
        with torch.no_grad():
            ids = mapper.render(kf.K, kf.cam_to_world, w, h, return_ids=True).ids.numpy()  # [h, w]
        if ids.shape != sup.masks.shape[1:]:
            raise ValueError(f"multiview: keyframe {k} masks are {sup.masks.shape[1:]}, render is {ids.shape}")
        for i, m in enumerate(sup.masks):
            g = np.unique(cell[ids[m & (ids >= 0)]])
            rows.append(np.full(len(g), len(keys))), cols.append(g)
            keys.append((k, i))
    r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    c = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    return keys, csr_matrix((np.ones(len(r), np.float32), (r, c)), shape=(len(keys), max(V, 1)))


def associate(mapper, sset, min_jaccard: float = 0.5, max_scale_ratio: float = 1.5) -> tuple[list, np.ndarray]:
    """-> (keys [(keyframe, mask)], component label per key): masks of one object across views."""
    keys, A = mask_gaussians(mapper, sset)
    if not keys:
        return keys, np.zeros(0, np.int64)
    inter = (A @ A.T).tocoo()
    size = np.asarray(A.sum(1)).ravel()
    i, j, n = inter.row, inter.col, inter.data
    jac = n / np.maximum(size[i] + size[j] - n, 1)
    kf = np.array([k for k, _ in keys])
    scale = np.array([float(sset.by_keyframe[k].scales[m]) for k, m in keys])
    ratio = np.maximum(scale[i], scale[j]) / np.maximum(np.minimum(scale[i], scale[j]), 1e-9)
    link = (i < j) & (kf[i] != kf[j]) & (jac >= min_jaccard) & (ratio <= max_scale_ratio)
    return keys, _merge_one_per_keyframe(len(keys), kf, i[link], j[link], jac[link])


def _merge_one_per_keyframe(n: int, kf: np.ndarray, i: np.ndarray, j: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Greedy union-find over links, best first, that never puts two masks of one keyframe in one
    object: chains of links through nested part / object / group masks would otherwise merge a
    whole table-top into one component. -> label per mask [n], 0..G-1."""
    parent = np.arange(n)
    frames = [{int(k)} for k in kf]

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for e in np.argsort(-score, kind="stable"):
        a, b = root(int(i[e])), root(int(j[e]))
        if a == b or frames[a] & frames[b]:
            continue
        if len(frames[a]) < len(frames[b]):
            a, b = b, a
        parent[b] = a
        frames[a] |= frames[b]
    roots = np.array([root(a) for a in range(n)])
    return np.unique(roots, return_inverse=True)[1].reshape(-1)


def aggregate_multiview(mapper, sset, min_jaccard: float = 0.5, max_scale_ratio: float = 1.5,
                        keys: tuple | None = None) -> dict:
    """Replace each mask's embedding by its object's multi-view mean over the masks with their own
    embedding (the per-view embedding stays in `embeddings_view`), refit the PCA and return
    statistics. `keys`: an association already made, (keys, labels) of `associate`."""
    from .pca import PCA

    keys, labels = keys if keys is not None else associate(mapper, sset, min_jaccard, max_scale_ratio)
    if not keys:
        return {"masks": 0, "objects": 0}
    for k in {k for k, _ in keys}:
        sup = sset.by_keyframe[k]
        if getattr(sup, "embeddings_view", None) is None:
            sup.embeddings_view = sup.embeddings.clone()
    view = torch.stack([sset.by_keyframe[k].embeddings_view[m] for k, m in keys]).float()  # [K, D]
    area = torch.tensor([float(sset.by_keyframe[k].masks[m].sum()) * bool(sset.by_keyframe[k].owned()[m])
                         for k, m in keys])  # masks without their own embedding do not vote
    lab = torch.from_numpy(labels)
    G = int(lab.max()) + 1
    mean = torch.zeros(G, view.shape[1]).index_add_(0, lab, view * area[:, None])
    mean = torch.nn.functional.normalize(mean, dim=-1, eps=1e-8)
    for r, (k, m) in enumerate(keys):
        sset.by_keyframe[k].embeddings[m] = mean[lab[r]]
    all_emb = torch.cat([s.embeddings for s in sset.by_keyframe.values() if len(s.embeddings)])
    sset.pca.raw = [all_emb]
    if len(all_emb) >= 2:
        sset.pca.pca = PCA.fit(all_emb, sset.pca.k)
        sset.pca.version += 1
    sizes = np.bincount(labels)
    return {"masks": len(keys), "objects": G, "views_per_object_mean": round(float(sizes.mean()), 2),
            "views_per_object_max": int(sizes.max())}
