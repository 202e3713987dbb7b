"""The stages of a query after reasoning, each with a small typed result (Grounder._ground runs
them in the paper's order): reference view and scale s* -> the most relevant pixel -> the groups of
instance features at s* -> mask votes, the piece in space and the boxes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..field.sampling import interval_centre
from ..geometry.conventions import pixels_to_points
from ..geometry.points import within
from .boxes import connected_to, group_boxes, robust_inliers
from .carve import MaskView, mask_votes
from .grouping import Groups
from .phrases import names_match
from .relevancy import CANONICAL, relevancy
from .result import GroundedObject

SHARE_POINTS = 1000   # carve_views: a mask's points it measures the share near the instance with


@dataclass
class MaskCandidate:
    """A keyframe's supervision mask most similar to the target text."""

    similarity: float
    pixels: int
    keyframe: object     # rg_core.map Keyframe
    index: int           # mask index in the keyframe's supervision
    scale: float         # the mask's physical scale (m)


@dataclass
class Reference:
    """The reference view: the keyframe and mask most like the target, and the target scale s*."""

    target: torch.Tensor            # [D] embedding of the target name
    candidates: list[MaskCandidate]
    keyframe: object
    mask_index: int
    similarity: float
    scale: float
    mask: torch.Tensor              # [H, W] bool, the reference mask
    name: str = ""                  # the target's name (masks taught as another name are no candidates)
    group_scale: float = 0.0        # instance features are read here: the middle of the training interval
                                    # above s* (field.sampling.interval_centre), where its mask groups


@dataclass
class Peak:
    """The most relevant pixel of the reference view and what lies there."""

    render: object                  # the field render of the reference keyframe
    px: int
    py: int
    relevancy: float
    instance: torch.Tensor          # [Di] instance feature at (px, py) and s*
    anchor: np.ndarray              # [3] world point of the rendered surface there
    has_depth: bool                 # the render has depth at the pixel (anchor is meaningful)


def similarities(sup, target: torch.Tensor, name: str = "") -> torch.Tensor:
    """[M] each mask's embedding against the target text [D]; -1 for a mask a person taught as
    another name than `name` (teach.py): a taught "red cup" is no candidate for "blue cup", however
    alike the two texts embed."""
    sims = torch.nn.functional.normalize(sup.embeddings.float(), dim=-1) @ target.float()
    if sup.taught is not None and name:
        other = [bool(t) and not names_match(name, t) for t in sup.taught]
        sims = torch.where(torch.tensor(other, dtype=torch.bool), torch.full_like(sims, -1.0), sims)
    return sims


def mask_candidates(g, target: torch.Tensor, name: str = "") -> list[MaskCandidate]:
    """Per keyframe, its mask most similar to the target text [D] (named `name`: similarities)."""
    by_index = {kf.index: kf for kf in g.mapper.keyframes}
    out = []
    for k, sup in g.mapper.supervision.by_keyframe.items():
        if k not in by_index or not len(sup.embeddings):
            continue
        sims = similarities(sup, target, name)
        i = int(sims.argmax())
        out.append(MaskCandidate(float(sims[i]), int(sup.masks[i].sum()), by_index[k], i, float(sup.scales[i])))
    return out


def reference(g, name: str) -> Reference | str:
    """The keyframe whose mask embedding is most like `name` (among near-ties the one that sees it
    largest) and that mask's scale s*; a message when no mask is similar enough."""
    target = g.encode([name])[0]
    cands = mask_candidates(g, target, name)
    top = max((c.similarity for c in cands), default=-2.0)
    best = max((c for c in cands if c.similarity >= top - 0.02), key=lambda c: c.pixels, default=None)
    sim = -2.0 if best is None else best.similarity
    if best is None or sim < g.gcfg.min_mask_similarity:
        return f"no part of the map looks like {name!r}: best mask similarity {sim:.2f} < {g.gcfg.min_mask_similarity}"
    sup = g.mapper.supervision.by_keyframe[best.keyframe.index]
    return Reference(target, cands, best.keyframe, best.index, best.similarity, best.scale,
                     torch.from_numpy(sup.masks[best.index]), name, interval_centre(sup.scales, best.scale))


def peak(g, ref: Reference, name: str) -> Peak:
    """The peak of the 3x3 mean relevancy, inside the reference mask where it has rendered pixels
    (features bleed a pixel or two over borders). Relevancy is computed over the mask's box grown
    by 2 pixels only: the same peak as over the whole view, in a fraction of the time."""
    kf = ref.keyframe
    w, h = kf.size
    fr = g.render_keyframe(kf)
    in_mask = ref.mask.shape == (h, w) and bool((ref.mask & (fr.alpha > g.gcfg.mask_alpha)).any())
    y0, y1, x0, x1 = 0, h, 0, w
    if in_mask:
        ys, xs = torch.nonzero(ref.mask, as_tuple=True)
        y0, y1 = max(int(ys.min()) - 2, 0), min(int(ys.max()) + 3, h)
        x0, x1 = max(int(xs.min()) - 2, 0), min(int(xs.max()) + 3, w)
    rel = g._relevancy(fr, name, ref.scale, (slice(y0, y1), slice(x0, x1)))   # [y1-y0, x1-x0]
    smooth = torch.nn.functional.avg_pool2d(rel[None, None], 3, 1, 1, count_include_pad=False)[0, 0]
    if in_mask:
        keep = ref.mask[y0:y1, x0:x1] & _renders_sensed(g, fr, kf, (slice(y0, y1), slice(x0, x1)))
        if not bool(keep.any()):
            keep = ref.mask[y0:y1, x0:x1]
        smooth = torch.where(keep, smooth, torch.full_like(smooth, -1.0))
    py, px = divmod(int(smooth.reshape(-1).argmax()), x1 - x0)
    value = float(rel[py, px])
    py, px = py + y0, px + x0
    z = float(fr.depth[py, px] / fr.alpha[py, px].clamp(min=1e-6))          # the surface there
    anchor = pixels_to_points(px, py, z, np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64))
    return Peak(fr, px, py, value, g.field.instance(fr.latent[py, px], ref.group_scale), anchor, z > 0)


def _renders_sensed(g, fr, kf, box) -> torch.Tensor:
    """[h', w'] bool over `box`: pixels where the render's surface is the one the keyframe's sensor
    read (within the mapper's depth tolerance), or that have no reading. Elsewhere the map renders
    what lies behind or in front of it (a thin rim, a floater), and a peak there anchors on that."""
    d = kf.depth[box]
    z = fr.depth[box] / fr.alpha[box].clamp(min=1e-6)
    return ~(d > 0) | ((z - d).abs() <= g.mapper.depth_tolerance(d))


def candidate_groups(g, ref: Reference, pk: Peak, max_results: int) -> tuple[Groups, list[tuple[np.ndarray, float]]]:
    """HDBSCAN groups at s* (near the reference mask when one object is sought) and the candidate
    member sets with their feature similarity: the group holding the peak's instance feature first;
    when no group holds it (HDBSCAN left that object as noise), the Gaussians around that feature."""
    region = (g.region(ref.keyframe, ref.mask.numpy(), pk.render.depth, pk.render.alpha, ref.scale)
              if max_results == 1 else None)
    groups = g.groups(ref.group_scale, region)
    sim = groups.centres @ pk.instance                                          # [G]
    order = torch.argsort(sim, descending=True).tolist()
    home = groups.containing(pk.instance)
    if home >= 0:
        order.remove(home)
        order.insert(0, home)
    chosen = [order[0]] if order else []
    if max_results > 1 and order:
        chosen = more_instances(g, groups, order, ref.target, g.encode(list(CANONICAL)), ref.scale, max_results)
    found = []
    if home < 0:
        # Too few Gaussians around the feature (a weakly trained field): the nearest cluster, or with
        # no cluster at all the 2 x min_cluster_size Gaussians nearest that feature.
        ball = groups.ball(pk.instance)
        mcs = g.gcfg.min_cluster_size
        if len(ball) >= mcs:
            found.append((ball, float(sim.max()) if len(sim) else 1.0))
            chosen = chosen[1:] if max_results > 1 else []
        elif not chosen and groups.features is not None and len(groups.features):
            found.append(groups.nearest(pk.instance, 2 * mcs))
    found += [(groups.members(gi, grow=g.gcfg.grow_groups), float(max(sim[gi], 0.0))) for gi in chosen]
    return groups, found


def more_instances(g, groups: Groups, order: list[int], target, canon, scale, k: int) -> list[int]:
    """Other groups as relevant as the best one ("the cups"): relevancy of each group's mean latent."""
    lat = g.field.latents
    scores = []
    for gi in order:
        members = groups.gaussians(np.nonzero(groups.labels == gi)[0])
        if not len(members):
            scores.append(0.0)
            continue
        z = g.field.language(lat[torch.from_numpy(members)].mean(0), scale)
        scores.append(float(relevancy(g._decompress(z), target, canon)))
    best = scores[0]
    chosen = [order[0]]
    for gi, s in sorted(zip(order[1:], scores[1:]), key=lambda x: -x[1]):
        if len(chosen) >= k:
            break
        if s >= g.gcfg.multi_instance_ratio * best and s > 0.5:
            chosen.append(gi)
    return chosen


def keyframe_view(kf, mask: np.ndarray) -> MaskView | None:
    """A keyframe's mask [h, w] as a voting view (its camera and depth); None when the mask is not
    at the keyframe's size."""
    if np.shape(mask) != tuple(kf.depth.shape):
        return None
    return MaskView(np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64), kf.depth.numpy(),
                    np.asarray(mask))


def mask_points(kf, mask: np.ndarray, at_most: int = 0) -> np.ndarray:
    """[P, 3] world points of a keyframe's mask [h, w] (its size) at the pixels with a depth reading;
    `at_most` > 0: every k-th of them, at most about twice that (enough to measure a share)."""
    d = kf.depth.numpy()
    vs, us = np.nonzero(np.asarray(mask, bool) & (d > 0))
    if at_most > 0:
        step = max(1, len(vs) // at_most)
        vs, us = vs[::step], us[::step]
    return pixels_to_points(us, vs, d[vs, us], np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64))


def carve_views(g, ref: Reference, anchor: np.ndarray | None = None) -> list[MaskView]:
    """The target's masks in up to `carve_views` keyframes, largest first: those whose best mask is
    about as similar to the target as the best one (the same object seen again). With
    `ground.instance_overlap` > 0 a mask counts only when that share of its 3D points lies within
    max(2 cm, s*/2) of `anchor` [P, 3] (default: the reference mask's points): the same instance. A
    keyframe then gives the most similar of its masks that is; a second lego brick across the room
    is not this one, and its masks would carve this one away."""
    from scipy.spatial import cKDTree

    n, share = g.gcfg.carve_views, g.gcfg.instance_overlap
    cands = ref.candidates
    if n <= 0 or not cands:
        return []
    floor = max(max(c.similarity for c in cands) - 0.02, g.gcfg.min_mask_similarity)
    if anchor is None:
        on_ref = ref.mask.shape == tuple(ref.keyframe.depth.shape)
        anchor = mask_points(ref.keyframe, ref.mask.numpy()) if on_ref and share > 0 else np.zeros((0, 3))
    check = share > 0 and len(anchor) > 0
    tol = max(0.02, 0.5 * ref.scale)
    near_anchor = cKDTree(np.asarray(anchor, np.float64)) if check else None   # one tree for every mask
    sup = g.mapper.supervision.by_keyframe
    picked = []                                                         # (pixels, keyframe, mask)
    for c in cands:
        if c.similarity < floor:
            continue
        kf, s = c.keyframe, sup[c.keyframe.index]
        if not check:
            options = [(c.similarity, c.index)]
        else:
            sims = similarities(s, ref.target, ref.name).numpy()
            options = [(float(sims[i]), int(i)) for i in np.flatnonzero(sims >= floor)]
        best = None                                                     # (similarity, overlap, index)
        for sim, i in options:
            if s.masks[i].shape != tuple(kf.depth.shape):
                continue
            f = 1.0
            if check:
                p = mask_points(kf, s.masks[i], SHARE_POINTS)
                f = float(np.mean(near_anchor.query(p, distance_upper_bound=tol)[0] <= tol)) if len(p) else 0.0
                if f < share:
                    continue
            if best is None or (sim, f) > best[:2]:
                best = (sim, f, i)
        if best is not None:
            picked.append((int(s.masks[best[2]].sum()), kf, s.masks[best[2]]))
    picked.sort(key=lambda x: -x[0])
    return [keyframe_view(kf, mask) for _, kf, mask in picked[:n]]


def objects(g, ref: Reference, pk: Peak, found: list[tuple[np.ndarray, float]], max_results: int,
            confidence: float) -> list[GroundedObject]:
    """Each candidate set voted on by the target's masks (carve what they see elsewhere; the first
    set also takes what several see inside), cut to its piece in space (the first: the piece the
    reference mask sees most, else the one under the peak), outliers dropped (with `outlier_mads`), boxed."""
    gs = g.mapper.gaussians
    means = gs.means.detach().numpy()                                                      # [N, 3]
    kf = ref.keyframe
    link = g.link_length()
    views = carve_views(g, ref)
    ref_view = keyframe_view(kf, ref.mask.numpy()) if g.gcfg.anchor_support else None
    border = g.vote_border() if views or ref_view is not None else 0
    tol = g.vote_depth_tol()
    def sizes(ids: np.ndarray) -> np.ndarray:  # [k] largest axis of some Gaussians (m)
        return gs.log_scales.detach()[torch.from_numpy(ids)].max(1).values.exp().numpy()

    out = []
    for n, (ids, s_g) in enumerate(found[:max_results]):
        # Another instance ("the cups") is voted on by the masks of that instance: those near its members.
        seen_by = views if n == 0 else carve_views(g, ref, means[ids])
        if seen_by:   # votes only where they can matter: the set and, for the first, within 4 s* of the peak
            near = (within(gs.means.detach(), pk.anchor, 4 * ref.scale)
                    if n == 0 and pk.has_depth else np.zeros(0, np.int64))
            cand = np.unique(np.concatenate([ids, near]).astype(np.int64))
            v = mask_votes(means[cand], seen_by, sizes(cand), border_px=border, depth_tol_abs=tol)
            ids = np.setdiff1d(ids, cand[v.carved(g.gcfg.min_mask_votes)])
            if n == 0:
                ids = np.union1d(ids, cand[v.voted(g.gcfg.min_mask_votes)])
        if link > 0 and len(ids) > 1:
            support = against = None
            if n == 0 and ref_view is not None:
                rv = mask_votes(means[ids], [ref_view], sizes(ids), border_px=border, depth_tol_abs=tol)
                support, against = rv.inside > 0, rv.outside > 0
            ids = ids[connected_to(means[ids], pk.anchor if n == 0 and pk.has_depth else None, link, support, against)]
        if g.gcfg.outlier_mads > 0:
            ids = ids[robust_inliers(means[ids], g.gcfg.outlier_mads)]
        if not len(ids):
            continue
        lo, hi, c, R, ext = group_boxes(means[ids])
        colors = (gs.colors.detach()[torch.from_numpy(ids)].clamp(0, 1) * 255).round().byte().numpy()
        out.append(GroundedObject(ids.astype(np.int64), means[ids].astype(np.float32), colors, lo, hi, c, R,
                                  ext, float(confidence) * pk.relevancy * s_g))
    return out
