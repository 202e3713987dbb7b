"""What people taught the map: a name for the object at a point ("this is my mug").

A taught object keeps what finds it again after the map changed (new frames, refinement, pruning,
eviction, a reload): the lineage ids of its Gaussians (GaussianModel.uids: the survivors of
refinement, pruning and eviction keep theirs, split children and clones their parent's), and for
when too few of them are left, the point a person showed, the object's physical scale, its box and
its mean instance feature at that scale. Where two taught objects touch, `held` keeps which
Gaussians the split between them gave each (while the same objects are taught), so the cut stays
where it was made as the map moves, and `cont` those that continue it past its end.
grounding/teach.py finds the object, relabels its masks and answers with it; this module only
holds the records, checks names and saves them with the map (store.py).
"""
from __future__ import annotations

import time
import unicodedata
from dataclasses import dataclass, field

import numpy as np
import torch

MAX_NAME_CHARS = 64


def check_name(name) -> str:
    """A taught name, whitespace collapsed; ValueError saying what is wrong (empty, longer than
    MAX_NAME_CHARS, control characters, no letter)."""
    if not isinstance(name, str):
        raise ValueError(f"a taught name must be a string, got {type(name).__name__}")
    if any(unicodedata.category(c).startswith("C") for c in name):
        bad = next(c for c in name if unicodedata.category(c).startswith("C"))
        raise ValueError(f"the name holds a control character ({bad!r}): give a plain name, e.g. 'blue mug'")
    clean = " ".join(name.split())
    if not clean:
        raise ValueError("empty name: say what the object is, e.g. 'blue mug'")
    if len(clean) > MAX_NAME_CHARS:
        raise ValueError(f"the name is {len(clean)} characters long; at most {MAX_NAME_CHARS} are accepted")
    if not any(c.isalpha() for c in clean):
        raise ValueError(f"the name {clean!r} holds no letter: say what the object is, e.g. 'blue mug'")
    return clean


@dataclass
class TaughtObject:
    """One object a person named. Map frame, metres."""

    name: str
    point: np.ndarray            # [3] the point shown (on the object's surface)
    scale: float                 # the physical scale its group was formed at
    lo: np.ndarray               # [3] its axis-aligned box when last found
    hi: np.ndarray               # [3]
    instance: np.ndarray         # [Di] its mean instance feature at `scale` when last found
    rule: str = ""               # how the scale was chosen (the answer's explanation says it)
    gaussians: int = 0           # its Gaussians when last found
    stamp: float = field(default_factory=time.time)
    uids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   # [G] its Gaussians' lineage ids
    held: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   # [H] lineage ids it won from taught neighbours
    cont: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   # [C] lineage ids past its end (locate.continued)
    seams: bool = False          # found split at concave seams (taught from a point answer that showed it so)

    @property
    def centre(self) -> np.ndarray:
        return (np.asarray(self.lo, np.float64) + np.asarray(self.hi, np.float64)) / 2

    def to_json(self) -> dict:
        return {"name": self.name, "point": np.round(self.point, 4).tolist(), "scale": round(float(self.scale), 4),
                "aabb": [np.round(self.lo, 4).tolist(), np.round(self.hi, 4).tolist()],
                "gaussians": int(self.gaussians), "rule": self.rule, "stamp": float(self.stamp)}


class TaughtSet:
    """The map's taught objects, in teaching order; `version` grows with every change (caches
    and the relabelled supervision follow it)."""

    def __init__(self):
        self.items: list[TaughtObject] = []
        self.version = 0

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self):
        return iter(self.items)

    def names(self) -> list[str]:
        return list(dict.fromkeys(t.name for t in self.items))

    def add(self, obj: TaughtObject) -> TaughtObject:
        """Keep `obj`; an earlier record of the same name (case aside) at the same place (its point
        inside obj's box) is replaced: teaching twice is teaching once."""
        same = obj.name.lower()
        lo, hi = np.asarray(obj.lo) - 0.01, np.asarray(obj.hi) + 0.01
        self.items = [t for t in self.items if not (t.name.lower() == same
                                                    and np.all(t.point >= lo) and np.all(t.point <= hi))]
        self.items.append(obj)
        self._changed()
        return obj

    def _changed(self) -> None:
        """Another set of objects: the splits between touching ones are made afresh."""
        for t in self.items:
            t.held = np.zeros(0, np.int64)
        self.version += 1

    def forget(self, name, key=str.lower) -> list[TaughtObject]:
        """Remove every object taught as `name` (the names `key` equates: case aside unless told,
        grounding/teach.py also equates "my mug" and "mugs"); ValueError naming what was taught
        when there is none."""
        want = key(check_name(name))
        gone = [t for t in self.items if key(t.name) == want]
        if not gone:
            taught = ", ".join(repr(n) for n in self.names()) or "nothing yet"
            raise ValueError(f"nothing was taught as {name!r} (taught: {taught})")
        self.items = [t for t in self.items if key(t.name) != want]
        self._changed()
        return gone

    def boxes(self, margin: float = 0.02) -> list[tuple[np.ndarray, np.ndarray]]:
        """The taught objects' boxes grown by `margin` (m): eviction never takes them."""
        return [(np.asarray(t.lo, np.float64) - margin, np.asarray(t.hi, np.float64) + margin) for t in self.items]

    def state_dict(self) -> dict:
        return {"objects": [{"name": t.name, "point": torch.from_numpy(np.asarray(t.point, np.float64)),
                             "scale": float(t.scale), "lo": torch.from_numpy(np.asarray(t.lo, np.float64)),
                             "hi": torch.from_numpy(np.asarray(t.hi, np.float64)),
                             "instance": torch.from_numpy(np.asarray(t.instance, np.float32)), "rule": t.rule,
                             "gaussians": int(t.gaussians), "stamp": float(t.stamp),
                             "uids": torch.from_numpy(np.asarray(t.uids, np.int64)),
                             "held": torch.from_numpy(np.asarray(t.held, np.int64)),
                             "cont": torch.from_numpy(np.asarray(t.cont, np.int64)), "seams": bool(t.seams)}
                            for t in self.items],
                "version": int(self.version)}

    @staticmethod
    def from_state_dict(d: dict | None) -> "TaughtSet":
        s = TaughtSet()
        for o in (d or {}).get("objects", []):
            s.items.append(TaughtObject(check_name(o["name"]), o["point"].numpy(), float(o["scale"]), o["lo"].numpy(),
                                        o["hi"].numpy(), o["instance"].numpy(), str(o.get("rule", "")),
                                        int(o.get("gaussians", 0)), float(o.get("stamp", 0.0)),
                                        o["uids"].numpy().astype(np.int64) if "uids" in o else np.zeros(0, np.int64),
                                        *(o[k].numpy().astype(np.int64) if k in o else np.zeros(0, np.int64)
                                          for k in ("held", "cont")), bool(o.get("seams", False))))
        s.version = int((d or {}).get("version", len(s.items)))
        return s
