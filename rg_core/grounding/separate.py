"""Split touching objects between the points a person gave them: colour-stretched geodesics.

Where the 2D masks joined two objects in every view (a knife's handle against a cup), the instance
field joins them too, and only the person's points tell them apart. Each Gaussian goes to the seed
with the shortest path over the Gaussians' k-nearest-neighbour graph, each step's length stretched
by the colour difference across it (x (1 + colour_weight x RGB distance + contrast_weight x that
distance over the typical step around its ends)), so the cut between touching objects follows
their colour edge rather than the midpoint between the seeds. The second term is the edge's
contrast: a printed box's own steps are as large as those around them, a box's edge against a
plain wooden block stands out (ycbv_0002).
"""
from __future__ import annotations

import numpy as np

SAME_PLACE = 0.03     # m: taught points this near are the same object (two names for it), not split
ADJACENT = 0.01       # m: taught groups this near touch, and split_touching splits them apart
NEIGHBOURS = 8        # graph neighbours per Gaussian
COLOUR_WEIGHT = 10.0  # path stretch per unit of RGB distance (0-sqrt(3)); 30 set a synthetic knife apart
                      # but moved a real pudding box into the wood block beside it (ycbv_0002)
CONTRAST_WEIGHT = 2.0  # path stretch per unit of contrast: RGB distance / the ends' median neighbour step
CONTRAST_FLOOR = 0.02  # the least typical step (RGB distance): a clean render's flat colour has none


def nearest_seed(points: np.ndarray, colours: np.ndarray, seeds: np.ndarray, k: int = NEIGHBOURS,
                 colour_weight: float = COLOUR_WEIGHT, fixed: np.ndarray | None = None,
                 contrast_weight: float = CONTRAST_WEIGHT) -> np.ndarray:
    """points [U, 3] (m), colours [U, 3] (0-1), seeds [S, 3] (m) -> [U] index of each point's seed.

    Each seed starts at the point nearest it, and at the points `fixed` [U] (seed index, -1: free)
    gives it: those keep their seed, and the paths of the others start from them too. Points the
    graph does not connect to any start go by straight-line distance to the nearest start."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    if len(pts) == 0:
        return np.zeros(0, np.int64)
    rgb = np.clip(np.asarray(colours, np.float64), 0.0, 1.0)
    k = min(k + 1, len(pts))
    d, nb = cKDTree(pts).query(pts, k=k)                                              # [U, k]
    rows = np.repeat(np.arange(len(pts)), k - 1)
    cols, dist = nb[:, 1:].reshape(-1), d[:, 1:].reshape(-1)
    step = np.linalg.norm(rgb[rows] - rgb[cols], axis=1)                               # [U (k-1)]
    typical = np.median(step.reshape(len(pts), k - 1), axis=1) if k > 1 else np.zeros(len(pts))   # [U]
    contrast = step / np.maximum(0.5 * (typical[rows] + typical[cols]), CONTRAST_FLOOR)
    w = dist * (1.0 + colour_weight * step + contrast_weight * contrast) + 1e-9
    graph = coo_matrix((w, (rows, cols)), shape=(len(pts),) * 2).tocsr()
    label = np.full(len(pts), -1, np.int64) if fixed is None else np.asarray(fixed, np.int64).copy()   # [U]
    for i, s in enumerate(seeds):
        label[int(np.argmin(np.linalg.norm(pts - np.asarray(s, np.float64), axis=1)))] = i
    start = np.flatnonzero(label >= 0)
    _, _, src = dijkstra(graph, directed=False, indices=start, min_only=True, return_predecessors=True)   # [U]
    far = src < 0
    if far.any():
        src[far] = start[cKDTree(pts[start]).query(pts[far])[1]]
    return label[src]


def split_touching(gs, own: list[tuple[object, np.ndarray]]) -> list[np.ndarray]:
    """own: (TaughtObject, ids [n] of its own group in the GaussianModel `gs`) per taught object ->
    [ids] in that order. Objects whose groups share Gaussians or touch (within ADJACENT), taught
    apart (points more than SAME_PLACE apart), have the union of their groups split between their
    points (nearest_seed): a handle the instance field gave the cup beside it goes back to the
    knife. What one of them holds stays its own: the Gaussians it won in the last split
    (TaughtObject.held: the paths start from them too, so the cut does not move with the map) and
    those it was continued by past its end (.cont: a tube's cap stays the tube's though another's
    point is nearer). Paths from those reach only Gaussians of the object's own group: the body by
    a tube's cap, not the cup a knife's handle touches. Sets .held."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    out = [ids for _, ids in own]
    if len(own) < 2:
        return out
    means = gs.means.detach().numpy().astype(np.float64)
    trees = [cKDTree(means[ids]) for _, ids in own]
    points = np.stack([np.asarray(t.point, np.float64) for t, _ in own])                # [T, 3]
    same = np.linalg.norm(points[:, None] - points[None], axis=-1) <= SAME_PLACE         # [T, T]
    place = same.argmax(1)        # one seed per place: two names taught at one point share a group
    pair = np.zeros_like(same)
    for i in range(len(own)):
        for j in range(i + 1, len(own)):
            pair[i, j] = same[i, j] or trees[i].sparse_distance_matrix(trees[j], ADJACENT).nnz > 0
    _, comp = connected_components(pair, directed=False)
    for c in np.unique(comp):
        members = np.flatnonzero(comp == c)
        seeds = np.unique(place[members])
        if len(seeds) < 2:
            continue
        union = np.unique(np.concatenate([own[m][1] for m in members]))                # [U]
        uids = gs.uids.numpy()[union]
        by = [[own[m] for m in members if place[m] == s] for s in seeds]               # (record, ids) per seed
        held, cont, mine = (np.stack([np.isin(x, np.concatenate([f(o) for o in os])) for os in by])
                            for x, f in ((uids, lambda o: o[0].held), (uids, lambda o: o[0].cont),
                                         (union, lambda o: o[1])))                          # [S, U] each
        rgb = gs.colors.detach().numpy()[union]
        near = [nearest_seed(means[union], rgb, points[seeds], fixed=np.where(h.sum(0) == 1, h.argmax(0), -1))
                for h in (held, held | cont)]                                               # [U] each
        near = np.where(mine[near[1], np.arange(len(union))], near[1], near[0])
        owner = seeds[np.where(cont.sum(0) == 1, cont.argmax(0), near)]
        for m in members:
            out[m] = union[owner == place[m]]
            own[m][0].held = np.unique(uids[owner == place[m]])
    return out
