"""Queries about objects in relation to others, answered over an object-level scene graph.

The graph: every name of the grounder's vocabulary grounded once as an explicit query; the answers
returned (not abstained: see confidence.py) that share most of their Gaussians are one object
holding every such name with its calibrated confidence. Each object has its centre, boxes, size and
basic colour term (perception.colour_names); edges: on and near. It is cached with the map and
rebuilt when the map or the field changes.

`answer` resolves what phrases.parse read. View-dependent words use the query's camera (the newest
keyframe unless the caller gives one) and the explanation says which; on / under / above / tall /
high use the map's up direction (geometry.conventions.up_direction of the keyframes).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..perception.colour_names import COLOUR_TERMS
from .appearance import object_colour
from .boxes import robust_inliers
from .phrases import Relational, _nth, _singular, core_name, is_thing_name
from .result import GroundedObject, GroundingResult

NEAR_GAP = 0.10        # metres between two objects' boxes that still count as near (counting, "all")
SURFACE_HOLDS = 3      # objects resting on a graph object that make it a surface, not a thing beside them
SAME_OBJECT = 0.5      # answers sharing this share of the smaller one's Gaussians are one object
MIN_GAUSSIANS = 5      # fewer Gaussians are a speck, not an object
# Supports a map rarely holds as an object: "on the table" with no table in the graph means on a surface.
SURFACES = ("table", "desk", "counter", "countertop", "worktop", "shelf", "surface", "floor", "ground", "bench")
# A ranking whose best two are this close is a tie, not an answer (the robot must not act on a coin
# toss): distances and heights within max(TIE_M, TIE_SHARE of the best's), tops within TIE_M, volumes
# within TIE_VOLUME of the best's (three axes of about TIE_SHARE each). A mapped object's centre and box
# move by about a centimetre between builds of the same scene (the Gaussians that survive).
TIE_M, TIE_SHARE, TIE_VOLUME = 0.01, 0.05, 0.15


@dataclass
class SceneObject:
    """One object of the graph: its Gaussians, every name it answered with its confidence, its
    geometry (map frame, metres) and colour."""

    names: list[tuple[str, float]]     # (name, confidence), most confident first
    obj: GroundedObject
    colour: str

    @property
    def name(self) -> str:
        return self.names[0][0]

    @property
    def centre(self) -> np.ndarray:
        return np.asarray(self.obj.obb_center, np.float64)

    @property
    def volume(self) -> float:
        """Of the axis-aligned box: the Gaussians cover only seen surfaces, and an oriented box
        fitted to a flat visible side has almost no volume."""
        return float(np.prod(np.maximum(np.asarray(self.obj.aabb_max) - np.asarray(self.obj.aabb_min), 1e-4)))

    def to_json(self) -> dict:
        return {"name": self.name, "names": [[n, round(c, 3)] for n, c in self.names], "colour": self.colour,
                "centre": self.centre.round(4).tolist(), "extent": np.asarray(self.obj.obb_extent).round(4).tolist(),
                "aabb": [np.asarray(v).round(4).tolist() for v in (self.obj.aabb_min, self.obj.aabb_max)],
                "gaussians": len(self.obj.gaussian_ids)}


def build_graph(g, names: list[str]) -> list[SceneObject]:
    """The taught objects first (each its own, a person's name first among its names), then every
    other name grounded once (explicit), answers sharing their Gaussians merged."""
    from . import teach

    objs: list[SceneObject] = []
    for t in g.mapper.taught:   # a person's word: however few Gaussians it has (speck=1)
        try:
            o = teach.resolve(g, t)
        except ValueError:
            continue
        _add(g, objs, t.name, GroundingResult(True, "", target=t.name, confidence=teach.TAUGHT_CONFIDENCE,
                                              objects=[o]), speck=1)
    taught = {core_name(n) for n in g.mapper.taught.names()}
    for name in dict.fromkeys(names):
        if core_name(name) not in taught:
            _add(g, objs, name, g._ground(name, "explicit", 1))
    return [SceneObject(sorted(o.names, key=lambda nc: (core_name(nc[0]) not in taught, -nc[1])), o.obj, o.colour)
            for o in objs] if taught else objs


def _add(g, objs: list[SceneObject], name: str, res: GroundingResult, speck: int = MIN_GAUSSIANS) -> bool:
    """Put an explicit answer for `name` into `objs`: a name more of the object whose Gaussians it
    shares (that object replaced, not changed: `objs` may copy a cached graph), else a new object.
    False when absent, not sure (below the calibrated threshold) or a speck (< `speck` Gaussians)."""
    if not res.success or len(res.objects[0].gaussian_ids) < speck:
        return False
    o = res.objects[0]
    ids = set(o.gaussian_ids.tolist())
    home = next((i for i, s in enumerate(objs) if len(ids & set(s.obj.gaussian_ids.tolist()))
                 >= SAME_OBJECT * min(len(ids), len(s.obj.gaussian_ids))), None)
    if home is not None:
        s = objs[home]
        objs[home] = SceneObject(sorted(s.names + [(name, float(res.confidence))], key=lambda nc: -nc[1]), s.obj, s.colour)
    else:
        objs.append(SceneObject([(name, float(res.confidence))], o, object_colour(g, o)))
    return True


def with_query_names(g, rq: Relational, objs: list[SceneObject]) -> list[SceneObject]:
    """The graph plus the query's own names it lacks (target, anchors: names of things, not
    descriptions), each grounded once as build_graph grounds the vocabulary's. The graph holds only
    names of the vocabulary; without scene names that is the household names the masks are nearest
    to, and the masks of an orange cup are nearest "orange", which abstains on it, as "cup" does
    beside it: so when a name's best guess has a colour that is itself a vocabulary name, the colour
    and the name together are asked too ("orange cup"). A new list: the cached graph is kept as is."""
    vocab = g.vocabulary()
    names = [n for n in dict.fromkeys((rq.target, *rq.anchors)) if n and is_thing_name(n, vocab) and not _match(objs, n)]
    if not names:
        return objs
    objs, colours = list(objs), {v.lower() for v in vocab if v.lower() in COLOUR_TERMS}
    for name in names:
        res = g._ground(name, "explicit", 1)
        if not _add(g, objs, name, res) and res.objects and colours:
            c = (object_colour(g, res.objects[0]).split() or [""])[-1]
            if c in colours and not name.startswith(c + " "):
                _add(g, objs, f"{c} {name}", g._ground(f"{c} {name}", "explicit", 1))
    return objs


def _is_a(n: str, name: str) -> bool:
    """`n` is a `name`: the same or ending in it ("blue cup" is a cup), singular or plural, or one of
    its WordNet hypernyms is ("banana": edible fruit, so a fruit; "hammer": hand tool, so a tool)."""
    from ..perception.knowledge import KnowledgeError, load_knowledge

    n = core_name(n)
    if n == name or n.endswith(" " + name):
        return True
    try:
        e = load_knowledge().entry(n) or {}
    except KnowledgeError:
        return False
    return any(h == name or h.endswith(" " + name) for h in e.get("hypernyms", []))


def for_graph(rq: Relational, objs: list[SceneObject], vocabulary=()) -> bool:
    """Whether the graph should answer `rq`: counting always (none is an answer); anything else when
    the target is any object, one the map holds or a name of a thing (phrases.is_thing_name: "the
    banana next to the lemon" on a map without one says so). Otherwise the phrase is a description
    ("small metal scoop on a handle", "the biggest squeezing tool, with a long bar") and takes the
    usual path."""
    return rq.count or not rq.target or bool(_match(objs, rq.target)) or is_thing_name(rq.target, vocabulary)


def _match(objs: list[SceneObject], name: str, colour: str = "") -> list[SceneObject]:
    """Objects that are a `name` (_is_a; "my mug" is a mug) and, when given, of that colour."""
    name = core_name(name)
    out = [o for o in objs if not name or any(_is_a(n, name) for n, _ in o.names)]
    if colour:
        out = [o for o in out if o.colour.split()[-1] == colour or colour in o.name.split()]
    return out


class _Geometry:
    """An object's extent along the map's up direction and its horizontal footprint (robust: 2nd and
    98th percentiles of its Gaussian centres)."""

    def __init__(self, o: SceneObject, up: np.ndarray, e1: np.ndarray, e2: np.ndarray):
        p = np.asarray(o.obj.points, np.float64)
        if not len(p):
            p = o.centre[None]
        h = p @ up
        self.bottom, self.top, self.middle = (float(v) for v in np.percentile(h, [2, 98, 50]))
        xy = np.stack([p @ e1, p @ e2], 1)
        self.lo, self.hi = np.percentile(xy, 2, 0), np.percentile(xy, 98, 0)
        self.xy = np.array([o.centre @ e1, o.centre @ e2])

    @property
    def height(self) -> float:
        return self.top - self.bottom

    def over(self, other: "_Geometry", margin: float = 0.02) -> bool:
        """This one's horizontal centre lies on `other`'s footprint."""
        return bool(np.all(self.xy >= other.lo - margin) and np.all(self.xy <= other.hi + margin))


def _vertical(rel: str, t: _Geometry, a: _Geometry, sunk: bool = True) -> bool:
    """on: resting on a's top (within 3 cm + 10 % of a's height, or, with `sunk`, sunk in by at most
    half its own height: the hidden bottom is not mapped; without, 1 cm: neighbours whose boxes
    overlap in height are not on each other); above: over a's footprint and clear of it (not resting
    on it); under: below a's middle, under its footprint."""
    if not t.over(a):
        return False
    if rel == "on":
        gap = t.bottom - a.top
        low = -0.5 * t.height - 0.02 if sunk else -0.01
        return low <= gap <= 0.03 + 0.1 * a.height and t.middle > a.middle
    if rel == "above":
        return t.bottom > a.top + 0.03 + 0.1 * a.height
    return t.top <= a.middle   # under


def _supports(base: _Geometry, t: _Geometry, ratio: float = 4.0) -> bool:
    """`t` rests on `base` as on a surface: on it, inside its footprint, and `base` spans at least
    `ratio` x its footprint (a table under a cup). A surface holds SURFACE_HOLDS such objects: a
    long spoon's box can hold a peach beside it, not three things."""
    area = lambda g: float(np.prod(np.maximum(g.hi - g.lo, 1e-3)))    # noqa: E731 - footprint (m2)
    inside = bool(np.all(t.lo >= base.lo - 0.02) and np.all(t.hi <= base.hi + 0.02))
    return inside and area(base) >= ratio * area(t) and _vertical("on", t, base)


def _is_surface(o: SceneObject, objs: list[SceneObject], G) -> bool:
    """`o` holds SURFACE_HOLDS or more of the other objects resting on it as on a surface (_supports)."""
    return sum(_supports(G(o), G(x)) for x in objs if x is not o) >= SURFACE_HOLDS


def _box_gap(a: SceneObject, b: SceneObject) -> float:
    """Distance between two axis-aligned boxes (0 when they overlap)."""
    amin, amax, bmin, bmax = (np.asarray(v, np.float64) for v in (a.obj.aabb_min, a.obj.aabb_max,
                                                                   b.obj.aabb_min, b.obj.aabb_max))
    lo = np.maximum(amin - bmax, bmin - amax)
    return float(np.linalg.norm(np.maximum(lo, 0.0)))


def _frame(up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit up and two horizontal axes."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return up, e1, np.cross(up, e1)


def graph_relations(objs: list[SceneObject], up: np.ndarray) -> list[tuple[int, str, int, float]]:
    """The graph's edges (subject, "on" | "near", object, box distance m): i on j when it rests on
    j's top over j's footprint; near when their boxes are within NEAR_GAP (listed once, i < j)."""
    frame = _frame(up)
    geo = [_Geometry(o, *frame) for o in objs]
    out = []
    for i, a in enumerate(objs):
        for j, b in enumerate(objs):
            if i == j:
                continue
            gap = _box_gap(a, b)
            if _vertical("on", geo[i], geo[j]):
                out.append((i, "on", j, gap))
            elif i < j and gap <= NEAR_GAP and not _vertical("on", geo[j], geo[i]):
                out.append((i, "near", j, gap))
    return out


def graph_json(objs: list[SceneObject], up: np.ndarray) -> dict:
    """The graph as JSON (`rg graph --json`): objects, up and relations by object index."""
    return {"up": np.round(up, 4).tolist(), "objects": [o.to_json() for o in objs],
            "relations": [{"subject": i, "predicate": p, "object": j, "distance": round(d, 4)}
                          for i, p, j, d in graph_relations(objs, up)]}


def answer(rq: Relational, objs: list[SceneObject], cam_to_world: np.ndarray, camera: str,
           max_results: int, query: str, up: np.ndarray | None = None) -> GroundingResult:
    """Resolve a parsed query over the graph's objects. `up` [3]: the map's up direction (None: the
    camera's -y)."""
    res = GroundingResult(False, "", query=query, target=rq.target)
    known = ", ".join(sorted({o.name for o in objs})) or "none"
    anchors, notes = [], []
    for a in rq.anchors:
        found = [o for o in objs if o.name == a] or sorted(_match(objs, a), key=lambda o: -o.names[0][1])
        support = rq.relation == "on" and _singular(a) in SURFACES
        if support:   # a support only by an object's own name, not a runner-up name (a clamp also 'table')
            found = [o for o in found if _is_a(o.name, _singular(a))]
        if not found and support:
            notes.append(f"no {a!r} among the map's objects: 'on the {a}' read as resting on a surface, "
                         f"not on another object")
            continue
        if not found:
            res.message = f"no {a!r} in the map to relate to (objects: {known})"
            res.explanation = rq.describe()
            return res
        anchors.append((a, found))
    on_surface = rq.relation == "on" and not anchors
    cands = [o for o in _match(objs, rq.target, rq.colour) if all(o is not f[0] for _, f in anchors)]
    what = " ".join(x for x in (rq.colour, rq.target or "object") if x)
    if not cands:   # counting a thing the map lacks is an answer, 0; a word no name of a thing is not
        thing = not rq.target or is_thing_name(rq.target)
        res.success = bool(rq.count and thing)
        res.message = f"{'0' if res.success else 'no'} {what!r} in the map (objects: {known})" + (
            "" if thing else f": {rq.target!r} is no name of the vocabulary or the name knowledge")
        res.explanation = rq.describe()
        return res
    notes += [f"{len(f)} {a!r} in the map: relating to the most certain ({f[0].names[0][1]:.2f})"
              for a, f in anchors if len(f) > 1]
    c2w = np.asarray(cam_to_world, np.float64)
    w2c = np.linalg.inv(c2w)
    cam = lambda p: w2c[:3, :3] @ p + w2c[:3, 3]                                  # noqa: E731 - world -> camera
    frame = _frame(up if up is not None else -c2w[:3, 1])
    geo = {id(o): _Geometry(o, *frame) for o in objs}
    G = lambda o: geo[id(o)]                                                        # noqa: E731
    ref = [f[0] for _, f in anchors]
    point = (ref[0].centre + ref[1].centre) / 2 if rq.relation == "between" else ref[0].centre if ref else None
    where = ""
    if ref and rq.relation not in ("on", "above", "under"):   # the surface an anchor rests on is not beside it
        base = [o for o in cands if any(_supports(G(o), G(r)) for r in ref) and _is_surface(o, objs, G)]
        if base:
            cands = [o for o in cands if all(o is not b for b in base)]
            notes.append(f"{', '.join(repr(b.name) for b in base)} left out: {' and '.join(repr(r.name) for r in ref)} "
                         f"rest{'s' if len(ref) == 1 else ''} on it")
    # a graph object holding others under a name no support has: a table's plane the 2D models named as a thing
    surf = [o for o in objs if _is_surface(o, objs, G) and not any(_is_a(o.name, w) for w in SURFACES)]
    if surf and (on_surface or (rq.superlative and not rq.target)):
        kept = [o for o in cands if all(o is not x for x in surf)]
        if len(kept) < len(cands):
            notes.append(f"{', '.join(repr(x.name) for x in surf)} left out: a surface holding "
                         f"{SURFACE_HOLDS} or more objects, not one of them")
        cands = kept
    if on_surface:   # the support itself is not an object of the map: standing on top of no other object but a surface
        cands = [o for o in cands if not any(x is not o and all(x is not y for y in surf)
                                             and _vertical("on", G(o), G(x), sunk=False) for x in objs)]
        where = f" on the {rq.anchors[0]}"
        if not cands and not rq.count:
            res.message = f"no {what!r}{where}"
            res.explanation = "; ".join([rq.describe(), res.message] + notes) + "."
            return res
    elif rq.relation:   # keep the candidates the relation holds for (near / between: all, ranked below)
        pc = cam(point)
        keep = {"left": lambda o: cam(o.centre)[0] < pc[0], "right": lambda o: cam(o.centre)[0] > pc[0],
                "front": lambda o: cam(o.centre)[2] < pc[2], "behind": lambda o: cam(o.centre)[2] > pc[2],
                **{r: (lambda o, r=r: _vertical(r, G(o), G(ref[0]))) for r in ("on", "above", "under")}
                }.get(rq.relation)
        if keep is None and (rq.count or rq.every or rq.superlative):   # near / between as a set: within NEAR_GAP
            keep = lambda o: all(_box_gap(o, r) <= NEAR_GAP for r in ref)                # noqa: E731
        if keep is not None:
            cands = [o for o in cands if keep(o)]
        anchor_words = " and ".join(repr(a) for a in rq.anchors)
        where = f" {rq.relation} {anchor_words}" + (f" seen from {camera}" if rq.relation in
                                                     ("left", "right", "front", "behind") else "")
        if not cands and not rq.count:
            res.message = f"no {what!r}{where}"
            res.explanation = "; ".join([rq.describe(), f"no {what!r}{where}"] + notes) + "."
            return res
    side_x = lambda o: float(np.arctan2(cam(o.centre)[0], cam(o.centre)[2]))      # noqa: E731 - bearing, left to right
    tied, tie = 1, ""   # how many lead the ranking within its tie tolerance (TIE_*), and that tolerance
    if rq.count or rq.every:
        chosen = sorted(cands, key=side_x)
        why = f"{len(chosen)} {what!r}{where} in the map"
    elif rq.ordinal:
        order = sorted(cands, key=side_x, reverse=rq.side == "right")
        if rq.ordinal > len(order):
            res.message = f"only {len(order)} {what!r}{where} in the map, no {_nth(rq.ordinal)} from the {rq.side}"
            res.explanation = rq.describe()
            return res
        chosen = [order[rq.ordinal - 1 if rq.ordinal > 0 else -1]]
        nth = "last" if rq.ordinal < 0 else _nth(rq.ordinal)
        why = f"{nth} of {len(order)} from the {rq.side}, seen from {camera}"
    elif rq.superlative:
        sup = rq.superlative
        val = {"biggest": lambda o: o.volume, "smallest": lambda o: o.volume, "tallest": lambda o: G(o).height,
               "shortest": lambda o: G(o).height, "highest": lambda o: G(o).top, "lowest": lambda o: G(o).top,
               "nearest_camera": lambda o: float(np.linalg.norm(cam(o.centre)))}[sup]
        chosen = cands = sorted(cands, key=lambda o: -val(o) if sup in ("biggest", "tallest", "highest") else val(o))
        v = [val(o) for o in cands]
        tol, tie = ((TIE_VOLUME * v[0], f"{TIE_VOLUME:.0%}") if sup in ("biggest", "smallest") else
                    (TIE_M, f"{100 * TIE_M:.0f} cm") if sup in ("highest", "lowest") else
                    (max(TIE_M, TIE_SHARE * v[0]), f"max({100 * TIE_M:.0f} cm, {TIE_SHARE:.0%})"))
        tied = sum(abs(x - v[0]) <= tol for x in v)
        vals = {"biggest": lambda o: f"{1e6 * o.volume:.0f} cm3", "smallest": lambda o: f"{1e6 * o.volume:.0f} cm3",
                "tallest": lambda o: f"{100 * G(o).height:.0f} cm tall",
                "shortest": lambda o: f"{100 * G(o).height:.0f} cm tall",
                "highest": lambda o: f"top at {G(o).top:.2f} m up", "lowest": lambda o: f"top at {G(o).top:.2f} m up",
                "nearest_camera": lambda o: f"{np.linalg.norm(cam(o.centre)):.2f} m"}
        fmt = vals[rq.superlative]
        why = f"{rq.superlative.replace('_', ' ')} of {len(cands)}: {fmt(chosen[0])}" + (
            f", next {fmt(cands[1])}" if len(cands) > 1 else "")
        why += f" ({camera})" if rq.superlative == "nearest_camera" else ""
    elif rq.relation and not on_surface:
        if rq.relation in ("on", "under", "above"):   # the one most squarely on / under the anchor
            d = sorted((float(np.linalg.norm(G(o).xy - G(ref[0]).xy)), i) for i, o in enumerate(cands))
            unit = "m from its centre"
        else:
            d = sorted((float(np.linalg.norm(o.centre - point)), i) for i, o in enumerate(cands))
            unit = "m"
        chosen = [cands[i] for _, i in d]   # ranked: max_results > 1 returns the runners-up too
        tied = sum(x - d[0][0] <= max(TIE_M, TIE_SHARE * d[0][0]) for x, _ in d)
        tie = f"max({100 * TIE_M:.0f} cm, {TIE_SHARE:.0%})"
        why = f"{where.strip()} ({d[0][0]:.2f} {unit}" + (
            f", next nearest {d[1][0]:.2f} m" if len(d) > 1 else "") + ")"
    else:   # attribute only ("the red cup"): the most certain
        chosen = sorted(cands, key=lambda o: (rq.colour not in o.name.split(), -o.names[0][1]))   # named so first
        why = f"{len(cands)} {what!r}{where} in the map" + (", the most certain" if len(cands) > 1 else "")
    chosen = chosen if rq.count or rq.every else chosen[:max(max_results, tied, 1)]
    if not chosen:   # counting nothing is an answer: zero
        res.success, res.message = True, f"0 {what!r}{where} in the map"
        res.explanation = "; ".join([rq.describe(), res.message] + notes) + "."
        return res
    res.success, res.objects = True, [o.obj for o in chosen]
    res.target = chosen[0].name
    res.confidence = min(c for o in chosen for n, c in o.names[:1])
    res.message = (f"{why}" if rq.count or rq.every else f"{res.target!r}: {why}") + f"; {len(res.objects)} group(s)"
    if tied > 1:   # a coin toss is no answer: say so, with every tied group
        res.success, res.target = False, rq.target
        n = [repr(o.name) for o in chosen[:tied]]
        why += f"; a tie: {', '.join(n[:-1])} and {n[-1]} within {tie} of each other, not choosing one"
        res.message = f"{why}; {len(res.objects)} group(s)"
    res.explanation = "; ".join([rq.describe(), why] + notes) + "."
    return res
