"""What a query computes from the map alone, kept between queries and dropped when what it is made
from changes.

Each table has a scope, the state it is made from:
- "map": the Gaussians (identity and in-place version of their tensors, their count), the field
  and the supervision: renders, clusters over the whole map, spacing, background, scene graph,
  answers;
- "supervision": the keyframes and their masks, embeddings and PCA basis, and what was taught
  (map/taught.py): vocabulary, up direction (its plane too, which refining barely turns),
  registration border, masks' points; a map that grows or is refined keeps them;
- "field": the field's rows (its revision: training, pruning, a scale or PCA refit): clusters of
  one region, keyed by the Gaussians in it, which the map growing elsewhere leaves valid.
The mapper's optimiser replaces its tensors on every step and pruning or adding Gaussians makes new
ones, so idle refinement still empties the "map" tables; in-place edits bump torch's `_version`. A
frame the map already explains changes none of these and keeps every table (a robot streaming
frames of a mapped room asks warm). Identity is held by weak references: a freed object whose
address is reused never passes for the old one.
"""
from __future__ import annotations

import weakref
from collections import OrderedDict

import torch


class TensorState:
    """The identity of some objects (and the in-place version of those that are tensors) at one moment."""

    def __init__(self, objects: tuple):
        self.refs = tuple(weakref.ref(t) for t in objects)
        self.versions = tuple(getattr(t, "_version", None) for t in objects)

    def same(self, objects: tuple) -> bool:
        return len(objects) == len(self.refs) and all(
            r() is t and getattr(t, "_version", None) == v for r, t, v in zip(self.refs, objects, self.versions))


class MapCache:
    """Named LRU tables, each valid for one state of its scope (SCOPE); `check({scope: (objects,
    counters)})` empties a scope's tables when its objects or counters changed. `enabled=False`
    keeps nothing (the uncached baseline and its tests)."""

    SCOPE = {"groups": "map", "renders": "map", "spacing": "map", "background": "map", "graph": "map",
             "vocabulary": "supervision", "border": "supervision", "up": "supervision", "clusters": "field",
             "taught": "map", "answers": "map",
             "mask_points": "supervision"}

    def __init__(self, enabled: bool = True, sizes: dict[str, int] | None = None):
        self.enabled = enabled
        self.sizes = {"groups": 16, "clusters": 16, "renders": 8, "spacing": 1, "border": 1, "vocabulary": 1,
                      "background": 8, "graph": 1, "up": 1, "taught": 64, "answers": 32, "mask_points": 1024,
                      **(sizes or {})}
        self.tables: dict[str, OrderedDict] = {k: OrderedDict() for k in self.sizes}
        self._states: dict[str, tuple[TensorState, tuple]] = {}
        self.hits = self.misses = self.invalidations = 0

    def check(self, scopes: dict[str, tuple[tuple, tuple]]) -> None:
        """scopes: {scope: (objects, counters)} as they are now; one invalidation counted per call
        that emptied something."""
        emptied = False
        for scope, (objects, counters) in scopes.items():
            st = self._states.get(scope)
            if st is not None and st[1] == counters and st[0].same(objects):
                continue
            for name, t in self.tables.items():
                if self.SCOPE.get(name, "map") == scope and t:
                    emptied = True
                    t.clear()
            self._states[scope] = (TensorState(objects), counters)
        self.invalidations += emptied

    def clear(self) -> None:
        for t in self.tables.values():
            t.clear()

    def get(self, table: str, key, make):
        """The value stored under `key`, else make() (stored unless the cache is disabled)."""
        t = self.tables[table]
        if self.enabled and key in t:
            t.move_to_end(key)
            self.hits += 1
            return t[key]
        self.misses += 1
        value = make()
        if self.enabled:
            t[key] = value
            while len(t) > self.sizes[table]:
                t.popitem(last=False)
        return value


def map_scopes(mapper, field) -> dict[str, tuple[tuple, tuple]]:
    """What each scope is made from now, for MapCache.check: {scope: (objects, counters)} of a map
    and its field (None: no field)."""
    m, f = mapper, field
    g = m.gaussians
    sset = m.supervision
    taught = getattr(m, "taught", None)
    sup = (len(m.keyframes), m.keyframes[-1].index if m.keyframes else -1,
           sset.serial if sset is not None else None,
           taught.version if taught is not None else 0)
    if sset is not None:
        sup += (len(sset.by_keyframe), sum(len(s.embeddings) for s in sset.by_keyframe.values()),
                tuple(s.serial for s in sset.by_keyframe.values()),
                getattr(sset.pca, "version", None), id(sset.pca.pca))
    tensors = (g.means, g.log_scales, g.quats, g.opacity_logits)
    rows: tuple = ()
    if f is not None:
        if len(f.latents) != len(g):
            f.sync()  # latents follow Gaussians added or pruned since the last training step
        tensors += (f.latents,)
        # A map snapshot's frozen field (map/snapshot.py) is named by the state it froze, so the
        # snapshots that share it keep the tables warm.
        rows = (getattr(f, "state_token", None) or id(f), f.revision, f.steps,
                f._pca[0] if getattr(f, "_pca", None) is not None else None, id(f.scale_tf))
    return {"map": (tensors, (len(g),) + sup + rows), "supervision": ((), sup),
            "field": ((f,) if f is not None and getattr(f, "state_token", None) is None else (), rows)}
