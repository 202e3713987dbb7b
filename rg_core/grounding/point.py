"""Point -> object, shaped like a /ground answer: the group of the object at a 3D point of the map
(a click in RViz, a keyframe's pixel; locate.py finds it), what the map thinks it is and how sure it
would be. A taught object answers with its taught name (teach.py)."""
from __future__ import annotations

import numpy as np
import torch

from ..geometry.conventions import pixels_to_points
from . import teach
from .locate import check_point, object_at
from .relevancy import CANONICAL, relevancy
from .result import GroundingResult

MAX_NAMES = 5          # name candidates an answer lists


def point_at_pixel(mapper, view: int, u: float, v: float) -> np.ndarray:
    """The 3D point (map frame) a keyframe's pixel (u, v) sees: its sensor depth there, else the
    map's rendered depth. ValueError for a keyframe the map lacks, a pixel off its image or no depth."""
    kf = next((k for k in mapper.keyframes if k.index == int(view)), None)
    if kf is None:
        have = [k.index for k in mapper.keyframes]
        raise ValueError(f"the map has no keyframe {view} (keyframes: {have[:8]}{' ...' if len(have) > 8 else ''})")
    w, h = kf.size
    if not (np.isfinite(u) and np.isfinite(v) and 0 <= u < w and 0 <= v < h):
        raise ValueError(f"pixel ({u:g}, {v:g}) is off keyframe {view}'s image ({w} x {h}): 0 <= u < {w}, 0 <= v < {h}")
    col, row = min(int(round(u)), w - 1), min(int(round(v)), h - 1)
    z = float(kf.depth[row, col])
    if not z > 0:
        with torch.no_grad():
            r = mapper.render(kf.K, kf.cam_to_world, w, h)
        a = float(r.alpha[row, col])
        z = float(r.depth[row, col]) / a if a > 0.5 else 0.0
    if not (np.isfinite(z) and z > 0):
        raise ValueError(f"keyframe {view} has no depth at pixel ({u:g}, {v:g}), and the map renders nothing there")
    return pixels_to_points(np.array([u]), np.array([v]), np.array([z]), np.asarray(kf.K, np.float64),
                            np.asarray(kf.cam_to_world, np.float64))[0]


def name_candidates(g, covering: list, k: int = MAX_NAMES) -> list[tuple[str, float]]:
    """What the map says the object is: the vocabulary's names by relevancy of the mean embedding of
    its masks in the views that see the point (`covering`: locate.covering_masks; the 2D models' word,
    or a person's where taught), most relevant first, [(name, relevancy)] (at most k). The field's
    rendered relevancy at those pixels says less: it is trained to the masks' embeddings, and a
    thin object's pixels blend with what lies around it."""
    names = g.vocabulary()
    sset = g.mapper.supervision
    rows = [sset.by_keyframe[kf.index].embeddings[m].float() for kf, m, _, _ in covering]
    if not rows or not names:
        return []
    emb = torch.nn.functional.normalize(torch.nn.functional.normalize(torch.stack(rows), dim=-1).mean(0), dim=-1)
    canon = g.encode(list(CANONICAL))
    scores = [float(relevancy(emb, t, canon)) for t in g.encode(names)]
    order = np.argsort(-np.asarray(scores), kind="stable")[:k]
    return [(names[j], round(scores[j], 4)) for j in order]


def point_answer(g, point, query: str = "") -> GroundingResult:
    """The object at `point` as a GroundingResult (success False with the reason for bad input or
    nothing mapped there): its group, what the map thinks it is (`names`) and how sure it would be
    (`confidence`: its explicit answer for the top name, when that answer is this object)."""
    res = GroundingResult(False, "", query=query or "point")
    not_ready = g._not_ready()
    if not_ready:
        res.message = not_ready
        return res
    g._check_cache()
    try:
        p = check_point(point)
        teach.refresh(g)
        obj, scale, rule, covering = object_at(g, p)
    except ValueError as exc:
        res.message = str(exc)
        return res
    res.objects, res.scale, res.point = [obj], scale, p.tolist()
    taught = teach.taught_at(g, obj)
    res.names = ([(t.name, teach.TAUGHT_CONFIDENCE) for t in taught]
                 + [nc for nc in name_candidates(g, covering) if nc[0] not in {t.name for t in taught}])
    res.names = res.names[:MAX_NAMES]
    where = "({:.3f}, {:.3f}, {:.3f})".format(*p)
    if taught:
        res.target, res.confidence = taught[0].name, teach.TAUGHT_CONFIDENCE
        res.evidence = {"taught": 1.0}
        sure = f"taught by a person as {taught[0].name!r}"
    elif res.names:
        res.target = res.names[0][0]
        ans = g._ground(res.target, "explicit", 1)
        same = ans.objects and len(np.intersect1d(ans.objects[0].gaussian_ids, obj.gaussian_ids)) >= \
            0.5 * min(len(ans.objects[0].gaussian_ids), len(obj.gaussian_ids))
        res.confidence = float(ans.confidence) if same else 0.0
        res.evidence = dict(ans.evidence) if same else {}
        sure = (f"the map's own answer for {res.target!r} is this object (confidence {res.confidence:.2f})" if same
                else f"the map's own answer for {res.target!r} is another object, so its confidence here is 0")
    else:
        sure = "the map has no names to offer"
    obj.confidence = res.confidence
    res.success = True
    res.message = f"{len(obj.gaussian_ids)} Gaussians at {where}; the map thinks it is {res.target or 'nothing it can name'!r}"
    res.explanation = (f"The object at {where}: the group of instance features at its {rule}, holding the "
                       f"Gaussian nearest the point, voted on by those masks and cut to its piece in space. "
                       f"Names by relevancy of its masks' embeddings: {', '.join(f'{n} {s:.2f}' for n, s in res.names) or 'none'}; {sure}.")
    return res
