"""Teach and forget: a person names the object at a point, and every query on the map uses it.

`teach` finds the object (locate.object_at, continued past a long object's ends), keeps what finds
it again (map/taught.py) and makes the name supervision: in every keyframe that sees the object, the
masks that are it (IoU >= RELABEL_IOU with its visible mask there; the visible mask itself is added
when none is) take the name's text embedding as their language target, the PCA basis is refitted
when it cannot hold that embedding, and the field keeps training on them. Until it has, `answer`
serves a query naming a taught object (or a close variant: "mug" and "my mug" find "blue mug", "the
mugs" all of them) from the taught group directly. `refresh` re-applies the labels when keyframes
were added or dropped; all is idempotent: the model's own embeddings of relabelled masks are kept
with the supervision, and `restore` puts them back.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..map.taught import TaughtObject, check_name
from .masks import result_masks
from .phrases import _singular, core_name, names_match
from .locate import check_point, continued, object_at, off_support
from .result import GroundedObject, GroundingResult
from .separate import split_touching

TAUGHT_CONFIDENCE = 0.95   # a person's word: right unless the object moved (bench_teach measures it)
RELABEL_IOU = 0.5          # a keyframe mask this like the object's visible mask is the object
ADD_BELOW_IOU = 0.8        # with no mask this like it, the visible mask itself joins the keyframe's
MIN_PIXELS = 30            # fewer visible pixels: the keyframe does not see the object
PCA_RESIDUAL = 0.25        # a taught embedding the basis reconstructs worse than this refits it
KEEP_SHARE = 0.5           # of a taught group's Gaussians (when last found) left: still the object by lineage


def _plural(query: str) -> bool:
    last = str(query).lower().strip(" ?.!,").split()[-1:] or [""]
    return _singular(last[0]) != last[0]


# ------------------------------------------------------------------------------ finding taught objects

def resolve(g, t: TaughtObject) -> GroundedObject:
    """The taught object's group in the map as it is now (cached with the map): its own group
    (`_own`), less what it shares with other taught objects and lies nearer to theirs (`split_touching`):
    two objects a person named apart are two, even where the 2D masks joined them in every view.
    Its record follows (box, feature, count, lineage), so eviction keeps protecting it.
    ValueError when it is no longer in the map."""
    g._check_cache()
    items = list(g.mapper.taught)
    if all(x is not t for x in items):
        items.append(t)
    key = ("all", g.mapper.taught.version, tuple((id(x), x.name, tuple(np.round(x.point, 5))) for x in items))
    found = g.cache.get("taught", key, lambda: _resolve_all(g, items))[id(t)]
    if isinstance(found, Exception):
        raise found
    return found


def _resolve_all(g, items: list[TaughtObject]) -> dict:
    """id(t) -> GroundedObject (or the ValueError saying it is gone) for every taught object."""
    gs = g.mapper.gaussians
    own, out = [], {}
    for t in items:
        try:
            own.append((t, _own(g, t)))
        except ValueError as exc:
            out[id(t)] = exc
    for (t, ids), sep in zip(own, split_touching(gs, own)):
        obj = _group(gs, sep if len(sep) else ids)
        feats = g.field.gaussian_instance(t.scale, torch.from_numpy(obj.gaussian_ids))
        t.instance = torch.nn.functional.normalize(feats.mean(0), dim=-1).numpy()
        obj.confidence = TAUGHT_CONFIDENCE
        out[id(t)] = obj
    return out


def _own(g, t: TaughtObject) -> np.ndarray:
    """The Gaussians [n] of the taught object alone: its lineage (t.uids) while at least KEEP_SHARE
    of those it had when last found are left, else found again at its point and scale (the lineage
    taken from there). Updates t's box, count and lineage. ValueError when nothing is left there."""
    gs = g.mapper.gaussians
    ids = np.flatnonzero(np.isin(gs.uids.numpy(), t.uids)) if len(t.uids) else np.zeros(0, np.int64)
    if not (len(ids) and len(ids) >= KEEP_SHARE * max(t.gaussians, 1)):
        try:
            ids, more, _, _ = _found(g, t.point, t.scale, t.seams)
        except ValueError:   # nothing within reach of the point any more: what is left in its box
            means = gs.means.detach().numpy()
            ids = np.flatnonzero(np.all((means >= t.lo - 0.01) & (means <= t.hi + 0.01), 1))
            if not len(ids):
                raise ValueError(f"the taught {t.name!r} is no longer in the map (nothing near "
                                 "({:.3f}, {:.3f}, {:.3f}))".format(*t.point)) from None
            more = np.zeros(0, np.int64)
        _take_lineage(g, t, ids, more)
    means = gs.means.detach().numpy()[ids]
    t.lo, t.hi, t.gaussians = means.min(0), means.max(0), len(ids)
    return np.asarray(ids, np.int64)


def _found(g, point, scale: float | None, seams: bool = False) -> tuple[np.ndarray, np.ndarray, float, str]:
    """The object at `point` (locate.object_at) continued past a long object's ends
    (locate.continued), then cut off the surface it rests on (locate.off_support: a cut group's
    end can link a probe's piece to what the tip lies on): (ids [n], those of them continuing it
    [c], its scale, the rule). `seams`: split at concave seams first, as the point answer a person
    saw was (otherwise split_touching parts touching taught objects: on bench_teach, with every
    object taught, the seam split cost 2 points of taught mIoU on seed 702 and ycbv_0002)."""
    obj, scale, rule, _ = object_at(g, point, scale=scale, cut_support=False, seams=seams)
    ids = continued(g, obj.gaussian_ids, scale)
    ids = ids[off_support(g, g.mapper.gaussians.means.detach().numpy(), ids)]
    more = np.setdiff1d(ids, obj.gaussian_ids)
    return ids, more, scale, rule + (f"; continued past its end by {len(more)} Gaussians" if len(more) else "")


def _take_lineage(g, t: TaughtObject, ids: np.ndarray, more: np.ndarray) -> None:
    """t's group is now the Gaussians ids [n], `more` [c] of them continuing it: their lineage ids,
    made theirs alone first (GaussianModel.isolate; records holding a replaced id take its replacement)."""
    gs = g.mapper.gaussians
    changed = gs.isolate(torch.from_numpy(np.asarray(ids, np.int64)))
    for x in g.mapper.taught if changed else ():
        for f in ("uids", "held", "cont"):
            add = [changed[u] for u in getattr(x, f).tolist() if u in changed]
            setattr(x, f, np.union1d(getattr(x, f), np.asarray(add, np.int64)) if add else getattr(x, f))
    t.uids, t.gaussians, t.cont = np.unique(gs.uids.numpy()[ids]), len(ids), np.unique(gs.uids.numpy()[more])


def _group(gs, ids: np.ndarray) -> GroundedObject:
    """A GroundedObject of the Gaussians ids [n] (their points, colours and boxes)."""
    from .boxes import group_boxes

    means = gs.means.detach().numpy()[ids].astype(np.float32)
    cols = (gs.colors.detach()[torch.from_numpy(ids)].clamp(0, 1) * 255).round().byte().numpy()
    return GroundedObject(ids, means, cols, *group_boxes(means), 1.0)


def taught_at(g, obj: GroundedObject) -> list[TaughtObject]:
    """Taught objects whose group shares most of `obj`'s Gaussians (or the smaller one's)."""
    out = []
    for t in g.mapper.taught:
        try:
            ids = resolve(g, t).gaussian_ids
        except ValueError:
            continue
        if len(np.intersect1d(ids, obj.gaussian_ids)) >= 0.5 * min(len(ids), len(obj.gaussian_ids)):
            out.append(t)
    return out


def answer_query(g, query: str, max_results: int = 1) -> GroundingResult | None:
    """Grounder._ground's first step on a map with taught objects: the labels brought up to date
    (`refresh`), then `answer` for a query that is a name ("my mug", "the mugs", "blue mug") rather
    than a relation, a count or a superlative (those go to the scene graph, which holds the taught
    objects)."""
    from .phrases import parse

    refresh(g)
    rq = parse(query)
    if rq is not None and not (rq.attribute_only and not rq.colour):
        return None
    return answer(g, query, max_results)


def answer(g, query: str, max_results: int = 1, reasoning: str = "") -> GroundingResult | None:
    """The answer to a query naming a taught object, from its taught group(s); None when it names
    none. A plural ("the mugs") or max_results > 1 returns every object taught under that name."""
    hits = [t for t in g.mapper.taught if names_match(query, t.name)]
    if not hits:
        return None
    exact = [t for t in hits if core_name(t.name) == core_name(query)]
    hits = exact or hits
    many = _plural(query) or max_results > 1
    objs, found, missing = [], [], []
    for t in reversed(hits):   # the most recently taught first
        try:
            objs.append(resolve(g, t))
            found.append(t)
        except ValueError as exc:
            missing.append(str(exc))
        if not many and objs:
            break
    if not objs:
        return GroundingResult(False, "; ".join(missing), query=query, target=hits[-1].name)
    if not many:
        objs, found = objs[:1], found[:1]
    elif max_results > 1 and not _plural(query):
        objs, found = objs[:max_results], found[:max_results]
    t = found[0]
    res = GroundingResult(True, "", query=query, target=t.name, confidence=TAUGHT_CONFIDENCE, objects=objs,
                          scale=float(t.scale), evidence={"taught": 1.0})
    n = sum(len(o.gaussian_ids) for o in objs)
    names = list(dict.fromkeys(x.name for x in found))   # "the screwdrivers": a flat and a phillips one
    if len(names) == 1:
        res.message = (f"{len(objs)} group(s) for {t.name!r}, {n} Gaussians; taught by a person"
                       + (f" ({len(found)} taught under that name)" if len(found) > 1 else ""))
    else:
        res.message = (f"{len(objs)} group(s) for {query.strip()!r}, {n} Gaussians; taught by a person as "
                       + ", ".join(repr(x) for x in names))
    res.explanation = ((reasoning + " " if reasoning else "") + " ".join(
        f"{x.name!r} was taught by a person at ({x.point[0]:.3f}, {x.point[1]:.3f}, {x.point[2]:.3f}); "
        f"found again there at its {x.rule or f'scale {x.scale:.3f} m'}." for x in found)
        + f" Confidence {TAUGHT_CONFIDENCE:.2f}: taught by a person.")
    return res


# ------------------------------------------------------------------------------ teaching

def teach(g, name: str, point=None, result: GroundingResult | None = None) -> tuple[TaughtObject, GroundingResult]:
    """Name the object at `point` [3] (map frame), or the first group of `result` (an earlier
    answer), `name`. -> (the record, the answer it gives now). ValueError for a bad name or point,
    nothing mapped there, or a map not ready to be queried; the map is then unchanged."""
    name = check_name(name)
    why = g._not_ready()
    if why:
        raise ValueError(f"cannot teach yet: {why}")
    g._check_cache()
    if (point is None) == (result is None):
        raise ValueError("teach: give a point or an answer, not both and not neither")
    shown = result is not None and result.point is not None
    if shown:   # a point answer (a click): taught as at its point, the group it showed (split at seams)
        point, result = result.point, None
    if result is not None:
        if not result.objects:
            raise ValueError("teach: the answer holds no object to name")
        o = result.objects[0]
        means = g.mapper.gaussians.means.detach().numpy()
        ids = o.gaussian_ids[o.gaussian_ids < len(means)]
        if not len(ids):
            raise ValueError("teach: the answer's Gaussians are no longer in the map; ground again")
        c = np.asarray(o.obb_center, np.float64)
        point = means[ids[np.argmin(np.linalg.norm(means[ids] - c, axis=1))]]
    p = check_point(point)
    ids, more, scale, rule = _found(g, p, result.scale if result is not None and result.scale > 0 else None, shown)
    if result is not None:
        rule = f"scale {scale:.3f} m: the scale of the answer it was taught from"
    feats = g.field.gaussian_instance(scale, torch.from_numpy(ids))
    box = g.mapper.gaussians.means.detach().numpy()[ids]
    t = TaughtObject(name, p, float(scale), box.min(0), box.max(0),
                     torch.nn.functional.normalize(feats.mean(0), dim=-1).numpy(), rule, len(ids), seams=shown)
    _take_lineage(g, t, ids, more)
    g.mapper.taught.add(t)
    apply(g)
    return t, answer(g, name)


def forget(g, name: str) -> list[TaughtObject]:
    """Forget every object taught as `name` (or a spelling core_name equates); ValueError when
    none was. Their masks get the model's own embeddings back."""
    gone = g.mapper.taught.forget(name, key=core_name)
    apply(g)
    return gone


# ------------------------------------------------------------------------------ supervision

def restore(sup):
    """A keyframe's supervision without teaching: added masks out, relabelled rows back to the
    model's embeddings. -> a new KeyframeSupervision (or `sup` itself when nothing was taught)."""
    if sup.taught is None:
        return sup
    keep = ~sup.added
    emb = sup.embeddings.clone()
    rows = torch.from_numpy(np.flatnonzero(sup.taught != ""))
    emb[rows] = sup.model[rows].to(emb)
    k = torch.from_numpy(keep)
    return dataclasses.replace(
        sup, masks=sup.masks[keep], scores=sup.scores[keep], levels=sup.levels[keep], scales=sup.scales[keep],
        embeddings=emb[k], embeddings_view=None if sup.embeddings_view is None else sup.embeddings_view[k],
        own=None if sup.own is None else sup.own[keep], taught=None, model=None, added=None)


def _label(sup, visible: np.ndarray, name: str, text: torch.Tensor, scale: float):
    """`sup` with its masks that are the object (visible [h, w]) labelled `name` (text [D])."""
    M = len(sup.scales)
    taught = sup.taught.copy() if sup.taught is not None else np.full(M, "", dtype=object)
    model = sup.model.clone() if sup.model is not None else sup.embeddings.clone().float()
    added = sup.added.copy() if sup.added is not None else np.zeros(M, bool)
    inter = (sup.masks & visible[None]).reshape(M, -1).sum(1)
    union = (sup.masks | visible[None]).reshape(M, -1).sum(1)
    iou = inter / np.maximum(union, 1)
    emb = sup.embeddings.clone()
    hit = np.flatnonzero((iou >= RELABEL_IOU) & (taught == ""))
    emb[torch.from_numpy(hit)] = text.to(emb)
    taught[hit] = name
    masks, scores, levels, scales = sup.masks, sup.scores, sup.levels, sup.scales
    ev, own = sup.embeddings_view, sup.own
    if not len(iou) or iou.max() < ADD_BELOW_IOU:
        masks = np.concatenate([masks, visible[None]])
        scores, levels = np.append(scores, np.float32(1.0)), np.append(levels, np.int8(1)).astype(np.int8)
        scales = np.append(scales, np.float32(scale)).astype(np.float32)
        emb = torch.cat([emb, text.to(emb)[None]])
        model = torch.cat([model, torch.zeros_like(model[:1])])
        ev = None if ev is None else torch.cat([ev, text.to(ev)[None]])
        own = None if own is None else np.append(own, True)
        taught, added = np.append(taught, name), np.append(added, True)
    return dataclasses.replace(sup, masks=masks, scores=scores, levels=levels, scales=scales, embeddings=emb,
                               embeddings_view=ev, own=own, taught=taught, model=model, added=added)


def apply(g, only: set[int] | None = None) -> dict:
    """Relabel the keyframes' masks for the taught objects now (restore first: idempotent), refit
    the PCA basis if a taught name's embedding does not fit it, and let the field follow. `only`:
    just these keyframes (new ones; the others keep their labels). -> {"keyframes": relabelled
    keyframes, "masks": masks labelled, "refit": bool}."""
    m = g.mapper
    sset = m.supervision
    stats = {"keyframes": 0, "masks": 0, "refit": False}
    if sset is None:
        return stats
    todo = [k for k in sset.by_keyframe if only is None or k in only]
    for k in todo:
        sset.by_keyframe[k] = restore(sset.by_keyframe[k])
    g.cache.clear()
    texts = {}
    kfs = {kf.index: kf for kf in m.keyframes}
    for t in m.taught:
        try:
            obj = resolve(g, t)
        except ValueError:
            continue
        text = texts.setdefault(t.name, torch.nn.functional.normalize(g.encode([t.name])[0].float(), dim=-1))
        one = GroundingResult(True, "", objects=[obj])
        for k in todo:
            sup, kf = sset.by_keyframe[k], kfs.get(k)
            if kf is None or sup.masks.shape[1:] != tuple(kf.depth.shape):
                continue
            w, h = kf.size
            _, _, vis = result_masks(m, g.gcfg, one, kf.K, kf.cam_to_world, w, h, depth=kf.depth.numpy())
            if int(vis.sum()) < MIN_PIXELS:
                continue
            new = _label(sup, vis, t.name, text, t.scale)
            stats["masks"] += int((new.taught == t.name).sum()) - (int((sup.taught == t.name).sum())
                                                                    if sup.taught is not None else 0)
            stats["keyframes"] += 1
            sset.by_keyframe[k] = new
    sset.pca.raw = [s.embeddings for s in sset.by_keyframe.values() if len(s.embeddings)]
    if texts and sset.pca.pca is not None:
        e = torch.stack(list(texts.values()))
        back = sset.pca.pca.inverse(sset.pca.pca.transform(e))
        if float((back - e).norm(dim=-1).max()) > PCA_RESIDUAL:
            from ..perception.pca import PCA

            sset.pca.pca = PCA.fit(torch.cat(sset.pca.raw), sset.pca.k)
            sset.pca.version += 1
            stats["refit"] = True
    sset.taught_state = (m.taught.version, tuple(sorted(sset.by_keyframe)))
    if g.field is not None:
        g.field.follow_supervision()
    g.cache.clear()
    if only is None:   # the masks now carry the names: find each object again with them, and keep that lineage
        for t in m.taught:
            try:
                ids, more, _, _ = _found(g, t.point, t.scale, t.seams)
            except ValueError:
                continue
            _take_lineage(g, t, ids, more)
        g.cache.clear()
    return stats


def refresh(g) -> bool:
    """Re-apply the labels when the taught objects or the supervised keyframes changed since they
    were applied (new keyframes, a dropped one, a reloaded map). True when it did."""
    sset = g.mapper.supervision
    if sset is None or (not len(g.mapper.taught) and getattr(sset, "taught_state", None) is None):
        return False
    now = (g.mapper.taught.version, tuple(sorted(sset.by_keyframe)))
    was = getattr(sset, "taught_state", None)
    if was == now:
        return False
    if was is not None and was[0] == now[0]:   # only keyframes came or went: label the new ones
        apply(g, only=set(now[1]) - set(was[1]))
    else:
        apply(g)
    return True
