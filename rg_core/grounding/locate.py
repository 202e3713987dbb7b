"""Where an object is: the Gaussian group of the object at a 3D point of the map, the lowest layer
of point and teach (point.py answers with it, teach.py finds taught objects again with it).

The scale rule (docs/pipeline.md, "Point and teach"): the keyframes that see the point (their depth
agrees with it) each give the supervision mask holding its pixel that is the whole object (the
largest at the group level, cut at depth jumps, unless it spans more than twice the object level's
scale: objects that touch, then the object level's; with no object-level mask there, the part
level's the same way), re-chosen by the views' agreement (_agreeing), and the object's scale s is
the median of those masks' physical scales; with no keyframe seeing the point, the median scale of
the map's object-level masks. The group is the cluster of instance features at s holding the
feature of the Gaussian nearest the point, voted on by those masks (seen outside them more often
than inside: carved; inside several, or inside the only one that sees it: joined), then by the
mask of every view that sees the group so far that is most the group (object_views), cut off the
surface it rests on (off_support), cut to its piece in space around the point, and split at the
concave seams between objects that touch (parts.py), keeping the part at the point.
"""
from __future__ import annotations

import numpy as np
import torch

from ..field.sampling import interval_centre
from ..geometry.conventions import in_image, project
from ..geometry.points import nearest, within
from .boxes import connected_to, group_boxes, robust_inliers
from .carve import mask_votes
from .parts import MIN_PART, part_at, seen_normals
from .result import GroundedObject
from .stages import keyframe_view, mask_points

NEAR_RADIUS = 0.05     # m: a point farther than this from every Gaussian holds nothing mapped
REACH, MIN_REACH = 4.0, 0.08   # the object's Gaussians lie within max(REACH x s, MIN_REACH) m of the point
VOTE_ROUNDS = 3        # votes by the point's views, then twice by the views that see the group
TOUCHING = 2.0         # a group-level mask this many times the object level's scale holds several objects
AGREE_ROUNDS, AGREE_POINTS = 3, 150   # _agreeing: re-choice rounds, points per mask it projects
NEAR_GROUP = 0.01      # m (+ the group's median Gaussian size): object_views' 'near the group'
LONG = 2.5             # continued: a group whose largest spread is this many times its second is long
PAST_MIN, PAST_INSIDE = 10, 0.7   # continued: Gaussians past an end worth a look; share of a join in the cylinder
LINK_STEPS = 6.0       # continued: the piece found past an end is linked by steps of this many group spacings
PROBES = 5             # continued: points past an end looked up; the piece most of them find is the one tested
RING = 0.03            # m: off_support fits the surface under an object to what lies this near it
LOW = 0.006            # m: off_support: a Gaussian this near that surface, coloured like it, is the surface's


def check_point(point) -> np.ndarray:
    """[3] float64, or ValueError saying what is wrong."""
    p = np.asarray(point, np.float64).reshape(-1) if np.size(point) else np.zeros(0)
    if p.shape != (3,):
        raise ValueError(f"a point has 3 coordinates (x, y, z in the map frame), got {np.size(point)}")
    if not np.isfinite(p).all():
        raise ValueError(f"the point ({', '.join(f'{v:g}' for v in p)}) has NaN or infinite coordinates: "
                         "give finite x, y, z in metres")
    return p


def covering_masks(g, point: np.ndarray) -> list[tuple[object, int, int, float]]:
    """(keyframe, mask index, level, scale) per keyframe that sees `point` [3]: its supervision mask
    that is the whole object at the point's pixel (_object_mask, then the views' agreement: _agreeing)."""
    sset = g.mapper.supervision
    out, sups, holds = [], [], []
    for kf in g.mapper.keyframes:
        sup = sset.by_keyframe.get(kf.index) if sset is not None else None
        if sup is None or not len(sup.scales):
            continue
        w, h = kf.size
        uv, z = project(point[None], np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64))
        if not in_image(uv, z, w, h)[0]:
            continue
        u, v = (int(x) for x in np.round(uv[0]))
        d = float(kf.depth[v, u])
        if not (d > 0 and abs(d - float(z[0])) <= float(g.mapper.depth_tolerance(torch.tensor(d)))):
            continue   # hidden in this view, or no reading: it cannot say what is there
        hold = np.flatnonzero(sup.masks[:, v, u]) if sup.masks.shape[1:] == (h, w) else np.zeros(0, np.int64)
        if not len(hold):
            continue
        out.append((kf, *_object_mask(sup, hold)))
        sups.append(sup)
        holds.append(hold)
    return _agreeing(out, sups, holds, points=lambda kf, j: g.mask_points(kf, j, AGREE_POINTS))


def _agreeing(covering: list, sups: list, holds: list, rounds: int = AGREE_ROUNDS, points=None) -> list:
    """`covering` with each view's mask re-chosen among the masks holding the point's pixel (`holds`)
    as the one that agrees best with the other views' choices: the mean over the other views of the
    F1 of (its points seen there inside their mask, their points seen here inside it); the whole
    object is the mask the views agree on, where one view's depth cut keeps a part or joins a
    neighbour. Starts from _object_mask's choice; ties keep it. `points(keyframe, mask index)`:
    the mask's points (default: mask_points of at most AGREE_POINTS)."""
    from .carve import sight

    if len(covering) < 2 or all(len(h) < 2 for h in holds):
        return covering
    V = len(covering)
    kfs = [c[0] for c in covering]
    Ks = np.stack([np.asarray(k.K, np.float64) for k in kfs])
    c2w = np.stack([np.asarray(k.cam_to_world, np.float64) for k in kfs])
    depths = [k.depth.numpy() for k in kfs]
    masks, pts = {}, {}       # (view, mask) -> [h, w] bool, its points [P, 3] (at most AGREE_POINTS)
    for a, (kf, hold) in enumerate(zip(kfs, holds)):
        for j in (hold if len(hold) > 1 else [covering[a][1]]):
            masks[a, int(j)] = sups[a].masks[j]
            pts[a, int(j)] = (points(kf, int(j)) if points is not None
                              else mask_points(kf, masks[a, int(j)], AGREE_POINTS))
    keys = list(pts)
    ends = np.cumsum([len(pts[k]) for k in keys])
    _, seen, r, u = sight(np.concatenate([pts[k] for k in keys]), Ks, c2w, depths, np.zeros(int(ends[-1])))  # [V, P]
    seen_in = {}              # (view, mask) -> per view: the rows, cols of its points seen there
    for k, e0, e1 in zip(keys, np.r_[0, ends[:-1]], ends):
        sl = slice(int(e0), int(e1))
        seen_in[k] = [(r[b, sl][seen[b, sl]], u[b, sl][seen[b, sl]]) for b in range(V)]
    choice = [int(c[1]) for c in covering]

    def inside(key, b, mask):   # of the points of `key` (view, mask) seen in view b, the share inside `mask`
        r, u = seen_in[key][b]
        return float(mask[r, u].mean()) if len(r) >= 5 else None

    for _ in range(rounds):
        new = []
        for a, hold in enumerate(holds):
            if len(hold) < 2:
                new.append(choice[a])
                continue
            best, best_score = choice[a], -1.0
            for j in [choice[a]] + [int(x) for x in hold if int(x) != choice[a]]:
                f1 = []
                for b in range(V):
                    if b == a:
                        continue
                    p = inside((a, j), b, masks[b, choice[b]])
                    q = inside((b, choice[b]), a, masks[a, j])
                    if p is not None and q is not None:
                        f1.append(2 * p * q / max(p + q, 1e-9))
                score = float(np.mean(f1)) if f1 else -1.0
                if score > best_score + 1e-9:
                    best, best_score = j, score
            new.append(best)
        if new == choice:
            break
        choice = new
    return [(c[0], j, int(sup.levels[j]), float(sup.scales[j])) for c, sup, j in zip(covering, sups, choice)]


def _object_mask(sup, hold: np.ndarray) -> tuple[int, int, float]:
    """(index, level, scale) of the mask among `hold` (a pixel's masks) that is its whole object:
    the largest of the group level (2: cut at depth jumps), unless it spans more than
    TOUCHING x the object level's (1) scale (objects that touch), then the largest of level 1;
    with no level-1 mask there (the object level cut nothing, and equal masks keep the group's),
    the largest of level 0 when the group's spans more than TOUCHING x its scale (a banana against
    a wood block on YCB-Video: one group and object mask, a banana part mask); else the largest
    of any level."""
    by = {lv: max((j for j in hold if int(sup.levels[j]) == lv), key=lambda j: int(sup.masks[j].sum()), default=None)
          for lv in (2, 1, 0)}
    finer = by[1] if by[1] is not None else by[0]   # no object-level mask: it equalled the group's
    i = by[2]
    if i is None:
        i = by[1]
    elif finer is not None and sup.scales[i] > TOUCHING * sup.scales[finer]:
        i = finer
    if i is None:
        i = max(hold, key=lambda j: int(sup.masks[j].sum()))
    return int(i), int(sup.levels[i]), float(sup.scales[i])


def object_views(g, points: np.ndarray, sizes: np.ndarray, min_seen: int = 5) -> list:
    """MaskViews of the object whose Gaussians are `points` [n, 3] (sizes [n] m): in each keyframe
    that sees at least `min_seen` of them, among the masks holding at least half of the seen ones the
    one that is most the group: the best F1 of (the seen ones' share inside it, its points' share
    within NEAR_GROUP + their median size of one of them); ties keep _object_mask's choice."""
    from .carve import sight

    sset = g.mapper.supervision
    kfs = [kf for kf in g.mapper.keyframes if sset is not None and kf.index in sset.by_keyframe
           and sset.by_keyframe[kf.index].masks.shape[1:] == tuple(kf.depth.shape)]
    if not kfs or not len(points):
        return []
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    reach = NEAR_GROUP + float(np.median(sizes))   # a mask's point this near a Gaussian of the group is the group's
    on, seen, rows, cols = sight(points, np.stack([np.asarray(k.K, np.float64) for k in kfs]),
                                 np.stack([np.asarray(k.cam_to_world, np.float64) for k in kfs]),
                                 [k.depth.numpy() for k in kfs], 1.5 * np.asarray(sizes, np.float64))
    out = []
    for kf, s_, r, u in zip(kfs, seen, rows, cols):
        if int(s_.sum()) < min_seen:
            continue
        sup = sset.by_keyframe[kf.index]
        share = sup.masks[:, r[s_], u[s_]].mean(1)                              # [M]
        hold = np.flatnonzero(share >= 0.5)
        if len(hold) > 1:   # the mask that is most the group: F1 of (share of the group in it, share of it near the group)
            near = []
            for j in hold:
                q = g.mask_points(kf, j, AGREE_POINTS)
                near.append(float((tree.query(q, distance_upper_bound=reach)[0] <= reach).mean()) if len(q) else 0.0)
            f1 = 2 * share[hold] * np.asarray(near) / np.maximum(share[hold] + np.asarray(near), 1e-9)
            first = _object_mask(sup, hold)[0]
            best = int(hold[int(np.argmax(f1))])
            out.append(keyframe_view(kf, sup.masks[best if f1.max() > f1[list(hold).index(first)] + 1e-9 else first]))
        elif len(hold):
            out.append(keyframe_view(kf, sup.masks[hold[0]]))
    return [v for v in out if v is not None]


def object_scale(g, covering: list) -> tuple[float, str]:
    """The object's scale s (m) and the rule that chose it (module docstring)."""
    if covering:
        s = float(np.median([c[3] for c in covering]))
        return s, (f"scale {s:.3f} m: the median of the {len(covering)} keyframe masks holding the point "
                   f"(the whole object's in each view)")
    sset = g.mapper.supervision
    obj = [s.scales[s.levels == 1] for s in sset.by_keyframe.values()] if sset is not None else []
    obj = np.concatenate(obj) if obj else np.zeros(0)
    s = float(np.median(obj)) if len(obj) else 0.1
    return s, f"scale {s:.3f} m: no keyframe sees the point, the median scale of the map's object masks"


def _group_scale(g, covering: list, scale: float) -> float:
    """Where the instance features of an object at `scale` are read: the middle of the interval
    training samples above it (field.sampling.interval_centre, as explicit answers) in the view of
    the covering mask of that scale; `scale` itself when no covering mask has it."""
    for kf, _, _, s in covering:
        if np.float32(s) == np.float32(scale):
            return interval_centre(g.mapper.supervision.by_keyframe[kf.index].scales, s)
    return scale


def object_at(g, point, scale: float | None = None, rule: str = "", cut_support: bool = True,
              seams: bool = True) -> tuple[GroundedObject, float, str, list]:
    """The object at `point` [3] (map frame): (its group, its scale s, the rule that chose s, the
    covering masks: covering_masks).
    `scale` given (a taught object found again): that scale. `cut_support`: cut the surface it rests
    on (off_support; teaching cuts it after continued, which looks past an end without it).
    `seams`: split it at concave seams from what it touches (parts.part_at; teaching does without:
    separate.split_touching parts taught objects that touch by their points and colours).
    ValueError when nothing is mapped within NEAR_RADIUS of the point."""
    p = check_point(point)
    gs = g.mapper.gaussians
    means = gs.means.detach().numpy()                                             # [N, 3]
    d, i = nearest(means, p[None], 1) if len(means) else (np.full((1, 1), np.inf), np.zeros((1, 1), np.int64))
    if not d[0, 0] <= NEAR_RADIUS:
        raise ValueError("nothing mapped within {:.0f} cm of ({:.3f}, {:.3f}, {:.3f})".format(100 * NEAR_RADIUS, *p))
    seed = int(i[0, 0])
    covering = covering_masks(g, p)
    if scale is None:
        scale, rule = object_scale(g, covering)
    c = g.gcfg
    region = np.zeros(len(means), bool)
    region[within(gs.means.detach(), p, max(REACH * scale, MIN_REACH))] = True
    region[seed] = True
    at = _group_scale(g, covering, scale)
    groups = g.groups(at, region)
    feat = g.field.gaussian_instance(at, torch.tensor([seed]))[0]
    home = groups.containing(feat)
    if home >= 0:
        ids = groups.members(home, grow=c.grow_groups)
    else:
        ids = groups.ball(feat)
        if len(ids) < c.min_cluster_size and groups.features is not None and len(groups.features):
            ids = groups.nearest(feat, 2 * c.min_cluster_size)[0]
    ids = np.union1d(ids, [seed]).astype(np.int64)
    sizes = lambda x: gs.log_scales.detach()[torch.from_numpy(x)].max(1).values.exp().numpy()  # noqa: E731
    cand = np.nonzero(region)[0]
    views = [v for v in (keyframe_view(kf, g.mapper.supervision.by_keyframe[kf.index].masks[m])
                         for kf, m, _, _ in covering) if v is not None]
    support = against = None
    grouped, inner = ids, np.zeros(0, np.int64)   # the field's group; what views from around put inside it
    for _ in range(VOTE_ROUNDS):   # the point's views first, then every view that sees the group so far
        if not views:
            break
        v = mask_votes(means[cand], views, sizes(cand), border_px=g.vote_border(), depth_tol_abs=g.vote_depth_tol())
        need = min(c.min_mask_votes, len(views))
        ids = np.union1d(np.setdiff1d(ids, cand[v.carved(need)]), cand[v.voted(need, by_seen=True)]).astype(np.int64)
        inner = np.union1d(inner, np.intersect1d(grouped, cand[v.interior]))
        ids = np.union1d(ids, np.setdiff1d(inner, cand[v.outside > v.inside]))   # one view cannot place it
        inside = np.isin(cand, ids)
        support, against = (v.inside > v.outside)[inside], (v.outside > v.inside)[inside]
        ids = cand[inside]
        views = object_views(g, means[ids], sizes(ids)) or views
    link = g.link_length()
    if link > 0 and len(ids) > 1:
        if cut_support:
            keep = off_support(g, means, ids)
            ids = ids[keep]
            support, against = (x[keep] if x is not None else None for x in (support, against))
        ids = ids[connected_to(means[ids], p, link, support, against)]
    if c.outlier_mads > 0 and len(ids) > 3:
        ids = ids[robust_inliers(means[ids], c.outlier_mads)]
    if seams and len(ids) >= 2 * MIN_PART:   # objects the masks joined: the one across no concave seam from the point
        keep = part_at(means[ids], seen_normals(g.mapper.keyframes, means[ids], sizes(ids)), p)
        if not keep.all():
            rule += f"; split at a concave seam from what it touches ({int(keep.sum())} of {len(ids)} Gaussians kept)"
            ids = ids[keep]
    if not len(ids):
        ids = np.array([seed], np.int64)
    lo, hi, centre, R, ext = group_boxes(means[ids])
    colors = (gs.colors.detach()[torch.from_numpy(ids)].clamp(0, 1) * 255).round().byte().numpy()
    return GroundedObject(ids, means[ids].astype(np.float32), colors, lo, hi, centre, R, ext, 1.0), scale, rule, covering


def off_support(g, means: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """bool [n] over a group's ids [n]: False for the Gaussians of the surface it rests on, seen
    through its holes and gaps (a fork's tines, a pair of scissors' handles), which its masks in
    every view hold. That surface is the plane fitted (robustly) to the Gaussians within RING of
    the group but not in it, when it faces up (within 20 degrees) and most of the group lies above
    it; a group Gaussian within LOW of it whose colour is nearer the surface's than the object's
    (the median of its Gaussians above LOW) is the surface's. Never more than half the group."""
    keep = np.ones(len(ids), bool)
    if len(ids) < 10:
        return keep
    lo, hi = means[ids].min(0) - RING, means[ids].max(0) + RING
    box = np.flatnonzero(((means >= lo) & (means <= hi)).all(1))                   # [B] near the group's box
    ring = np.setdiff1d(box[nearest(means[ids], means[box], 1)[0][:, 0] <= RING], ids)
    if len(ring) < 10:
        return keep
    pts, on = means[ring].astype(np.float64), np.ones(len(ring), bool)
    for _ in range(4):   # least squares, then again without what lies off the plane
        c = pts[on].mean(0)
        n = np.linalg.svd(pts[on] - c, full_matrices=False)[2][-1]
        res = np.abs((pts - c) @ n)
        on = res <= max(3 * 1.4826 * float(np.median(res[on])), 0.002)
        if on.sum() < 10:
            return keep
    up = g.up()
    n = n if n @ up >= 0 else -n
    h = (means[ids] - c) @ n                                                          # [n] above the plane
    if n @ up < np.cos(np.radians(20)) or on.mean() < 0.5 or np.mean(h > LOW) < 0.5:
        return keep
    col = g.mapper.gaussians.colors.detach()[torch.from_numpy(ids)].clamp(0, 1).numpy()   # [n, 3]
    surf = np.median(g.mapper.gaussians.colors.detach()[torch.from_numpy(ring[on])].clamp(0, 1).numpy(), 0)
    own = np.median(col[h > LOW], 0)
    drop = (h < LOW) & (np.linalg.norm(col - surf, axis=1) < np.linalg.norm(col - own, axis=1))
    return keep if drop.sum() > 0.5 * len(ids) else ~drop


def continued(g, ids: np.ndarray, scale: float) -> np.ndarray:
    """A long group [n] continued past its ends, where the masks cut off a tube's cap or a tool's
    tip (another colour, or hidden in some views). Past each end (within the group's length, in its
    cylinder: the group's 90th-percentile radius about its axis + 5 mm), the object found at the
    group's scale at the PROBES points there nearest the axis 2 cm on, each cut to its piece around
    its point (steps of LINK_STEPS x the group's median neighbour spacing, at least 2 mm: a shaft
    held up off the table it was grouped with). The piece most probes find (one probe can sit on
    the table a thin tip lies along) joins with its Gaussians in that cylinder, if they are at
    least PAST_INSIDE of the piece (the table under the end is mostly outside) and the piece is not
    long across the axis (a tool lying over the end). -> ids [m] (teaching uses it; point answers
    do without its lookups)."""
    means = g.mapper.gaussians.means.detach().numpy().astype(np.float64)             # [N, 3]
    if len(ids) < PAST_MIN:
        return ids
    a = _long_axis(means[ids])
    if a is None:
        return ids
    c = means[ids].mean(0)
    s = (means - c) @ a                                                               # [N] along the axis
    r = np.linalg.norm(means - c - s[:, None] * a, axis=1)                            # [N] from the axis
    length, radius = np.ptp(s[ids]), np.percentile(r[ids], 90) + 0.005
    link = max(LINK_STEPS * float(np.median(nearest(means[ids], means[ids], 2)[0][:, 1])), 0.002)   # [m]
    out = ids
    for e, end in ((1.0, s[ids].max()), (-1.0, s[ids].min())):
        past = e * (s - end)                                                          # [N] beyond this end
        cyl = (past > -radius) & (past <= length) & (r <= radius)
        cand = np.setdiff1d(np.flatnonzero(cyl & (past > 0)), out)
        if len(cand) < PAST_MIN:
            continue
        pieces = []
        for k in cand[np.argsort(np.abs(past[cand] - 0.02) + r[cand], kind="stable")[:PROBES]]:
            new = np.setdiff1d(object_at(g, means[k], scale=scale, cut_support=False, seams=False)[0].gaussian_ids, out)
            pieces.append(new[connected_to(means[new], means[k], link)] if len(new) > 1 else new)
        votes = [sum(_same(p, q) for q in pieces) for p in pieces]
        new = pieces[int(np.argmax(votes))]                                           # the first of the most found
        inside = new[cyl[new]]
        if len(inside) >= PAST_MIN and len(inside) >= PAST_INSIDE * len(new) and _along(means[new], a):
            out = np.union1d(out, inside)
    return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Two sets of ids [n], [m] are one piece: they share at least half their union."""
    return len(np.intersect1d(a, b)) >= 0.5 * max(len(np.union1d(a, b)), 1)


def _long_axis(points: np.ndarray) -> np.ndarray | None:
    """The unit axis [3] of points [n, 3] whose largest spread is LONG x their second, else None."""
    if len(points) < 3:
        return None
    w, V = np.linalg.eigh(np.cov((points - points.mean(0)).T))                        # ascending
    return V[:, -1] if w[-1] >= LONG ** 2 * max(w[-2], 1e-12) else None


def _along(points: np.ndarray, axis: np.ndarray, max_deg: float = 30.0) -> bool:
    """points [n, 3] are not long (_long_axis), or long within max_deg of axis [3] (unit)."""
    a = _long_axis(points)
    return a is None or abs(float(a @ axis)) >= np.cos(np.radians(max_deg))
