"""Queries about objects in relation to others, answered over an object-level scene graph.

The graph: every name of the grounder's vocabulary grounded once as an explicit query; the answers
returned (not abstained: see confidence.py) that share most of their Gaussians are one object
holding every such name with its calibrated confidence. Each object has its centre, boxes, size and basic colour term (perception.colour_names).
It is cached with the map and rebuilt when the map or the field changes.

The rule parser (`parse`) reads: "how many X", "the biggest / smallest / tallest X", "the X nearest
to me / the camera", "the X closest to / next to / near / beside the Y", "the X between the Y and the
Z", "the X left of / right of / in front of / behind the Y", and colour words before the target
("the red cup"). A query it does not read as one of these (a plain name, a description) is not a
relational query and takes the usual path. View-dependent words use the query's camera (the newest
keyframe unless the caller gives one) and the explanation says which.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..perception.colour_names import COLOUR_TERMS, colour_histogram
from .boxes import group_boxes, robust_inliers
from .result import GroundedObject, GroundingResult

ANY = ("object", "thing", "item", "one", "objects", "things", "items")
SUPERLATIVES = {"biggest": "biggest", "largest": "biggest", "smallest": "smallest", "tiniest": "smallest",
                "tallest": "tallest", "highest": "tallest", "shortest": "shortest", "lowest": "shortest"}
RELATIONS = {"closest to": "near", "nearest to": "near", "next to": "near", "near": "near", "beside": "near",
             "close to": "near", "to the left of": "left", "left of": "left", "to the right of": "right",
             "right of": "right", "in front of": "front", "behind": "behind", "between": "between"}
_REL_RE = "|".join(sorted((re.escape(k) for k in RELATIONS), key=len, reverse=True))
CAMERA_WORDS = ("me", "the camera", "camera", "you", "the robot", "us")
SAME_OBJECT = 0.5      # answers sharing this share of the smaller one's Gaussians are one object


@dataclass
class Relational:
    """A parsed relational query."""

    target: str                        # the name sought; "" = any object
    colour: str = ""                   # a basic colour term the target must have
    relation: str = ""                 # near | left | right | front | behind | between
    anchors: list[str] = field(default_factory=list)
    superlative: str = ""              # biggest | smallest | tallest | shortest | nearest_camera
    count: bool = False

    @property
    def attribute_only(self) -> bool:
        return not (self.relation or self.superlative or self.count)

    def describe(self) -> str:
        parts = [f"target: {self.target or 'any object'}"]
        if self.colour:
            parts.append(f"colour: {self.colour}")
        if self.relation:
            parts.append(f"relation: {self.relation} " + " and ".join(repr(a) for a in self.anchors))
        if self.superlative:
            parts.append(f"superlative: {self.superlative.replace('_', ' ')}")
        if self.count:
            parts.append("count")
        return "; ".join(parts)


def _strip(phrase: str) -> str:
    p = re.sub(r"^(the|a|an|any|all( the)?)\s+", "", phrase.strip(" ?.!,"))
    return re.sub(r"\s+(are there|is there|do you see|in the (scene|map|room))$", "", p).strip()


def _target(phrase: str) -> tuple[str, str]:
    """'red cup' -> ('cup', 'red'); 'object' -> ('', '')."""
    words = _strip(phrase).split()
    colour = words.pop(0) if len(words) > 1 and words[0] in COLOUR_TERMS else ""
    name = " ".join(words)
    return ("" if name in ANY else _singular(name)), colour


def _singular(name: str) -> str:
    if name.endswith("ies"):
        return name[:-3] + "y"
    if name.endswith(("ches", "shes", "xes", "ses")):
        return name[:-2]
    return name[:-1] if name.endswith("s") and not name.endswith("ss") else name


def parse(query: str) -> Relational | None:
    """A relational query, or None when the query is a plain name or description."""
    q = " ".join(query.lower().split()).strip(" ?.!")
    m = re.fullmatch(r"how many (?P<t>.+)", q)
    if m:
        t, c = _target(m["t"])
        return Relational(t, c, count=True)
    m = re.fullmatch(r"(?:the |a |an )?(?P<s>" + "|".join(SUPERLATIVES) + r"|nearest|closest) (?P<t>.+?)"
                     r"(?: (?:to|from) (?:me|the camera|the robot|you))?", q)
    if m and not re.search(r" (?:" + _REL_RE + r") ", f" {m['t']} "):
        t, c = _target(m["t"])
        sup = "nearest_camera" if m["s"] in ("nearest", "closest") else SUPERLATIVES[m["s"]]
        return Relational(t, c, superlative=sup)
    m = re.fullmatch(r"(?P<t>.+?) (?P<r>" + _REL_RE + r") (?P<a>.+?)(?: and (?P<b>.+))?", q)
    if m:
        t, c = _target(m["t"])
        rel = RELATIONS[m["r"]]
        anchors = [_strip(m["a"])] + ([_strip(m["b"])] if m["b"] else [])
        if rel == "between" and len(anchors) != 2:
            return None
        if rel != "between" and m["b"]:
            anchors = [_strip(m["a"] + " and " + m["b"])]
        if rel == "near" and anchors[0] in CAMERA_WORDS:
            return Relational(t, c, superlative="nearest_camera")
        if not all(anchors):
            return None
        return Relational(t, c, rel, [_singular(a) for a in anchors])
    t, c = _target(q)
    if c and len(q.split()) <= 4:   # "the red cup": a colour and a name (callers check it is not one name)
        return Relational(t, c)
    return None


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
                "gaussians": len(self.obj.gaussian_ids)}


def colour_term(rgb: np.ndarray) -> str:
    """uint8 [N, 3] -> the basic colour term most of them have, "light"/"dark" before a chromatic
    one that is bright or dark on average."""
    hist = colour_histogram(rgb)
    term = COLOUR_TERMS[int(np.argmax(hist))]
    v = float(np.asarray(rgb, np.float64).max(1).mean())
    if term in COLOUR_TERMS[:8] and v > 215:
        return f"light {term}"
    if term in COLOUR_TERMS[:8] and v < 90:
        return f"dark {term}"
    return term


def build_graph(g, names: list[str]) -> list[SceneObject]:
    """Ground every name once (explicit), merge answers sharing their Gaussians."""
    objs: list[SceneObject] = []
    gs = g.mapper.gaussians
    for name in dict.fromkeys(names):
        res = g._ground(name, "explicit", 1)
        if not res.success:   # absent, or not sure (below the calibrated threshold): not in the graph
            continue
        o = res.objects[0]
        ids = set(o.gaussian_ids.tolist())
        home = next((s for s in objs if len(ids & set(s.obj.gaussian_ids.tolist()))
                     >= SAME_OBJECT * min(len(ids), len(s.obj.gaussian_ids))), None)
        if home is not None:
            home.names.append((name, float(res.confidence)))
            home.names.sort(key=lambda nc: -nc[1])
            continue
        keep = o.gaussian_ids[robust_inliers(gs.means.detach().numpy()[o.gaussian_ids])]
        colour = colour_term((gs.colors.detach()[keep].clamp(0, 1) * 255).round().byte().numpy()) if len(keep) else ""
        objs.append(SceneObject([(name, float(res.confidence))], o, colour))
    return objs


def _is_a(n: str, name: str) -> bool:
    """`n` is a `name`: the same or ending in it ("blue cup" is a cup), singular or plural, or one of
    its WordNet hypernyms is ("banana": edible fruit, so a fruit; "hammer": hand tool, so a tool)."""
    from ..perception.knowledge import KnowledgeError, load_knowledge

    n = _singular(n)
    if n == name or n.endswith(" " + name):
        return True
    try:
        e = load_knowledge().entry(n) or {}
    except KnowledgeError:
        return False
    return any(h == name or h.endswith(" " + name) for h in e.get("hypernyms", []))


def _match(objs: list[SceneObject], name: str, colour: str = "") -> list[SceneObject]:
    """Objects that are a `name` (_is_a) and, when given, of that colour."""
    name = _singular(name)
    out = [o for o in objs if not name or any(_is_a(n, name) for n, _ in o.names)]
    if colour:
        out = [o for o in out if o.colour.split()[-1] == colour or colour in o.name.split()]
    return out


def answer(rq: Relational, objs: list[SceneObject], cam_to_world: np.ndarray, camera: str,
           max_results: int, query: str) -> GroundingResult:
    """Resolve a parsed query over the graph's objects."""
    res = GroundingResult(False, "", query=query, target=rq.target)
    known = ", ".join(sorted({o.name for o in objs})) or "none"
    anchors = []
    for a in rq.anchors:
        found = sorted(_match(objs, a), key=lambda o: -o.names[0][1])
        if not found:
            res.message = f"no {a!r} in the map to relate to (objects: {known})"
            res.explanation = rq.describe()
            return res
        anchors.append((a, found))
    cands = [o for o in _match(objs, rq.target, rq.colour) if all(o is not f[0] for _, f in anchors)]
    what = " ".join(x for x in (rq.colour, rq.target or "object") if x)
    if not cands:
        res.message = f"no {what!r} in the map (objects: {known})"
        res.explanation = rq.describe()
        return res
    notes = [f"{len(f)} {a!r} in the map: relating to the most certain ({f[0].names[0][1]:.2f})"
             for a, f in anchors if len(f) > 1]
    w2c = np.linalg.inv(np.asarray(cam_to_world, np.float64))
    cam = lambda p: w2c[:3, :3] @ p + w2c[:3, 3]                                  # noqa: E731 - world -> camera
    if rq.count:
        chosen, why = cands, f"{len(cands)} {what!r} in the map"
    elif rq.superlative:
        key = {"biggest": lambda o: -o.volume, "smallest": lambda o: o.volume,
               "tallest": lambda o: cam(o.centre)[1] - np.asarray(o.obj.obb_extent).max() / 2,
               "shortest": lambda o: -(cam(o.centre)[1] - np.asarray(o.obj.obb_extent).max() / 2),
               "nearest_camera": lambda o: float(np.linalg.norm(cam(o.centre)))}[rq.superlative]
        cands = sorted(cands, key=key)
        chosen = cands[:1]
        vals = {"biggest": lambda o: f"{1e6 * o.volume:.0f} cm3", "smallest": lambda o: f"{1e6 * o.volume:.0f} cm3",
                "nearest_camera": lambda o: f"{np.linalg.norm(cam(o.centre)):.2f} m"}
        fmt = vals.get(rq.superlative, lambda o: f"top {-cam(o.centre)[1]:.2f} m up in the camera")
        why = f"{rq.superlative.replace('_', ' ')} of {len(cands)}: {fmt(chosen[0])}" + (
            f", next {fmt(cands[1])}" if len(cands) > 1 else "")
        if rq.superlative in ("tallest", "shortest", "nearest_camera"):
            why += f" ({camera})"
    else:
        ref = [f[0] for _, f in anchors]
        if rq.relation == "between":
            point = (ref[0].centre + ref[1].centre) / 2
        else:
            point = ref[0].centre
        pc = cam(point)
        side = {"left": lambda o: cam(o.centre)[0] < pc[0], "right": lambda o: cam(o.centre)[0] > pc[0],
                "front": lambda o: cam(o.centre)[2] < pc[2], "behind": lambda o: cam(o.centre)[2] > pc[2]}
        if rq.relation in side:
            cands = [o for o in cands if side[rq.relation](o)]
            if not cands:
                res.message = f"no {what!r} {rq.relation} of {rq.anchors[0]!r} seen from {camera}"
                res.explanation = rq.describe()
                return res
        d = sorted((float(np.linalg.norm(o.centre - point)), i) for i, o in enumerate(cands))
        chosen = [cands[d[0][1]]]
        target = " and ".join(repr(a) for a in rq.anchors)
        why = f"{rq.relation} {target} ({d[0][0]:.2f} m" + (f", next nearest {d[1][0]:.2f} m" if len(d) > 1 else "") + ")"
        if rq.relation in side:
            why += f", seen from {camera}"
    chosen = chosen[:max(max_results, 1)] if not rq.count else chosen
    res.success, res.objects = True, [o.obj for o in chosen]
    res.target = chosen[0].name
    res.confidence = min(c for o in chosen for n, c in o.names[:1])
    res.message = (f"{why}" if rq.count else f"{res.target!r}: {why}") + f"; {len(res.objects)} group(s)"
    res.explanation = "; ".join([rq.describe(), why] + notes) + "."
    return res
