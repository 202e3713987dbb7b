"""What a query reads from the map besides its Gaussians, made from the map alone and kept in the
Grounder's MapCache (cache.py says when each is dropped): the vocabulary, clusters of instance
features at a scale over a region, field renders of keyframes, the map's spacing, up direction and
scene graph, the vote border; and the picture of the scene an image reasoner is shown. Each takes
the Grounder (`g`), as the stages do; the Grounder's methods of the same names call them.
"""
from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import torch

from ..geometry.conventions import backproject, up_direction
from ..geometry.points import map_spacing, within
from ..util import torch_threads
from . import relations, stages
from .carve import mask_depth_offsets, registration_border
from .grouping import Groups, cluster_instances
from .vocabulary import build_vocabulary


def _spread(items: list, n: int) -> list:
    """Up to n items spread evenly from the first to the last, in order."""
    if not items:
        return []
    return [items[i] for i in sorted({round(float(i)) for i in np.linspace(0, len(items) - 1, min(n, len(items)))})]


def scene_image(g, max_views: int = 4) -> np.ndarray:
    """-> [H, W, 3] uint8 RGB: up to `max_views` keyframes spread evenly over the map's keyframes,
    tiled 2 x 2 at their working resolution (one keyframe alone when there is one): what an image
    reasoner is shown of the scene before the target, and so the reference view, is known."""
    kfs = g.mapper.keyframes
    if not kfs:
        raise ValueError("scene_image: the map has no keyframes")
    pick = _spread(kfs, max_views)
    h, w = pick[0].rgb.shape[:2]
    tiles = []
    for kf in pick:
        img = (kf.rgb.detach().float().clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()  # [h, w, 3]
        if img.shape[:2] != (h, w):  # keyframes of another working size: fit the first one's
            import cv2

            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        tiles.append(img)
    if len(tiles) == 1:
        return tiles[0]
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % 2)
    rows = [np.concatenate(tiles[i:i + 2], axis=1) for i in range(0, len(tiles), 2)]
    return np.ascontiguousarray(np.concatenate(rows, axis=0))


def vocabulary(g) -> list[str]:
    """The names a reasoner may pick from (vocabulary.build_vocabulary; taught names first), cached
    with the supervision."""
    g._check_cache()
    sset = g.mapper.supervision
    n_masks = sum(len(s.embeddings) for s in sset.by_keyframe.values()) if sset is not None else 0
    taught = g.mapper.taught.names() if getattr(g.mapper, "taught", None) is not None else []
    key = (n_masks, tuple(taught), tuple(g.scene_names), tuple(g.gcfg.vocabulary), bool(g.gcfg.support_vocabulary))

    def make():   # taught names first: a person's word (grounding/teach.py)
        emb = torch.cat([s.embeddings for s in sset.by_keyframe.values()]) if n_masks else torch.zeros(0, 1)
        return build_vocabulary(taught + list(g.scene_names), g.gcfg.vocabulary, emb, g.encode,
                                g.gcfg.support_vocabulary)
    return list(g.cache.get("vocabulary", key, make))


def groups(g, scale: float, region: np.ndarray | None = None) -> Groups:
    """Clusters of instance features at one scale, over the Gaussians in `region` (bool [N];
    None: all); cached until the map, the field or the region changes. Gaussians outside the
    region are left out (rows only for the region's Gaussians: Groups.ids), so they never join a group."""
    g._check_cache()
    N = len(g.mapper.gaussians)
    key = (round(scale, 4), N, None if region is None else np.packbits(region).tobytes())

    def cluster(idx: torch.Tensor | None) -> Groups:
        c = g.gcfg
        with torch_threads(g._outer_threads):
            feats = g.field.gaussian_instance(scale, idx)                # [N or M, Di]: the region's only
        return cluster_instances(feats, c.max_cluster_points, c.min_cluster_size, c.cluster_eps,
                                 seed=c.seed, method=c.cluster_method)

    def make() -> Groups:
        if region is None:
            return cluster(None)
        idx = np.nonzero(region)[0]                                         # [M]
        # The region's clusters depend on its Gaussians' field rows only: kept while the map grows
        # elsewhere (appended rows leave old ones as they were; cache.py, scope "field").
        digest = hashlib.blake2b(idx.astype(np.int64).tobytes(), digest_size=16).digest()
        sub = g.cache.get("clusters", (round(scale, 4), len(idx), digest),
                          lambda: cluster(torch.from_numpy(idx)))
        return dataclasses.replace(sub, ids=idx)
    return g.cache.get("groups", key, make)


def region(g, kf, mask: np.ndarray, depth: torch.Tensor, alpha: torch.Tensor, scale: float) -> np.ndarray | None:
    """Gaussians that can belong to the reference mask's object: within `region_scales` x s* of
    the 3D centroid of the mask (back-projected with the rendered depth), else within
    `cull_radius` m of it when that leaves out > 10 % of the map. None: all (no depth there)."""
    c = g.gcfg
    if (c.region_scales <= 0 and c.cull_radius <= 0) or mask.shape != tuple(depth.shape):
        return None
    sel = torch.from_numpy(mask) & (alpha > c.mask_alpha) & (depth > 0)
    if int(sel.sum()) < 3:
        return None
    pts = backproject(depth.numpy(), np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64))
    centre = np.median(pts[sel.numpy()], 0)                                        # [3] world
    means = g.mapper.gaussians.means.detach()
    r = c.region_scales * max(scale, 1e-3) if c.region_scales > 0 else c.cull_radius
    near = np.zeros(len(means), bool)
    near[within(means, centre, r)] = True
    return near if c.region_scales > 0 or c.min_cluster_size <= near.sum() < 0.9 * len(near) else None


def spacing(g) -> float:
    """The map's resolution (m): the median nearest-neighbour distance between Gaussians, at least
    their median largest axis (std dev), cached until the map changes (idle refinement moves
    Gaussians too: see rg_core/grounding/cache.py). A map seeded from depth has Gaussians about as
    far apart as they are large; a photo fit's density control clones small ones into clumps (median
    neighbour 1.4 mm, median axis 10 mm on YCB-Video 0002), and links of a few neighbour distances
    then cut each object into pieces (docs/pipeline.md, "Maps from photos")."""
    g._check_cache()

    def make() -> float:
        gs = g.mapper.gaussians
        nn = map_spacing(gs.means.detach().numpy(), seed=g.gcfg.seed)
        size = float(gs.scales.detach().max(1).values.median()) if len(gs) else 0.0
        return max(nn, size)

    return g.cache.get("spacing", g.gcfg.seed, make)


def link_length(g) -> float:
    """Longest step (m) of the chains that keep a group one piece in space (boxes.connected_to):
    ground.link_spacing map spacings, at least a photo map's depth resolution (0: no links).
    The photos place each Gaussian only that well along its ray, so shorter steps cut one object
    by depth error: on YCB-Video 0002 (0.23 m) the banana kept 205 of its 304 voted Gaussians."""
    link = g.gcfg.link_spacing * spacing(g)
    photo = (getattr(g.mapper, "built", None) or {}).get("photo") or {}
    return max(link, float(photo.get("depth_resolution_m", 0.0))) if link > 0 else 0.0


def vote_depth_tol(g) -> float:
    """Least depth difference (m) at which a keyframe's depth says a Gaussian is not its surface
    (carve.mask_votes' depth_tol_abs): carve's own 2 cm, or a photo map's depth resolution (the depth
    one pixel of disparity spans across its views, geometry.conventions.depth_resolution, recorded
    by photo_fit.photo_mapper) where that is coarser.
    A photo map's keyframe depth is its own expected depth, and the photos place an object's
    Gaussians only that well in depth."""
    from .carve import DEPTH_TOL_ABS

    photo = (getattr(g.mapper, "built", None) or {}).get("photo") or {}
    return max(DEPTH_TOL_ABS, float(photo.get("depth_resolution_m", 0.0)))


def vote_border(g) -> int:
    """Mask growth (px) for the votes: ground.vote_border_px, or with -1 the colour/depth
    registration offset measured on up to 6 keyframes spread over the map (their supervision
    masks against their depth), cached until the map changes."""
    if g.gcfg.vote_border_px >= 0:
        return int(g.gcfg.vote_border_px)
    g._check_cache()

    def make() -> int:
        sup = g.mapper.supervision
        kfs = [kf for kf in g.mapper.keyframes if sup is not None and kf.index in sup.by_keyframe]
        if not kfs:
            return 0
        pick = _spread(kfs, 6)
        offs = []
        for kf in pick:
            depth = kf.depth.numpy()
            masks = [m for m in sup.by_keyframe[kf.index].masks
                     if m.shape == depth.shape and 50 <= int(m.sum()) <= 0.5 * m.size]
            if masks:
                offs.append(mask_depth_offsets(depth, masks))
        return registration_border(np.concatenate(offs) if offs else np.zeros(0))

    return g.cache.get("border", g.gcfg.seed, make)


def render_keyframe(g, kf):
    """The field rendered from a keyframe (latent, colour, depth, alpha), cached per keyframe."""
    g._check_cache()
    w, h = kf.size
    def make():
        with torch_threads(g._outer_threads):
            return g.field.render(kf.K, kf.cam_to_world, w, h)
    return g.cache.get("renders", (kf.index, w, h), make)


def mask_points(g, kf, j: int, at_most: int) -> np.ndarray:
    """stages.mask_points of keyframe `kf`'s supervision mask j: [P, 3], kept with the supervision
    (a click's views and votes read the same masks' points again and again)."""
    g._check_cache()
    return g.cache.get("mask_points", (kf.index, int(j), int(at_most)),
                       lambda: stages.mask_points(kf, g.mapper.supervision.by_keyframe[kf.index].masks[j], at_most))


def scene_graph(g) -> list:
    """The map's objects (relations.build_graph over the vocabulary), cached with the map."""
    g._check_cache()
    names = g.vocabulary()
    return g.cache.get("graph", tuple(names), lambda: relations.build_graph(g, names))


def up(g) -> np.ndarray:
    """The map's up direction [3] from its keyframes' poses, and its largest plane where they leave
    the pitch open (geometry.conventions.up_direction). Kept while the keyframes are (the floor or
    table a growing map refines barely turns)."""
    g._check_cache()
    return g.cache.get("up", tuple(k.index for k in g.mapper.keyframes),
                       lambda: up_direction(np.stack([k.cam_to_world for k in g.mapper.keyframes]),
                                            g.mapper.gaussians.means.detach().numpy()))
