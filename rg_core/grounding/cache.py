"""What a query computes from the map alone, kept between queries and dropped when the map or the
feature field changes.

The key is the identity and in-place version counter of the tensors the results are made from
(Gaussian parameters, field latents) plus the counters that say the rest changed (Gaussians,
keyframes, supervision masks and PCA basis, field training steps). The mapper's optimiser
replaces its tensors on every step and pruning or adding Gaussians makes new ones, so idle
refinement, which changes neither the number of Gaussians nor the keyframes, still invalidates;
in-place edits bump torch's `_version`. A frame the map already explains changes none of these
and keeps the caches (a robot streaming frames of a mapped room asks warm). Identity is held by weak references: a freed tensor whose
address is reused never passes for the old one.
"""
from __future__ import annotations

import weakref
from collections import OrderedDict

import torch


class TensorState:
    """The identity and in-place version of some tensors at one moment."""

    def __init__(self, tensors: tuple[torch.Tensor, ...]):
        self.refs = tuple(weakref.ref(t) for t in tensors)
        self.versions = tuple(t._version for t in tensors)

    def same(self, tensors: tuple[torch.Tensor, ...]) -> bool:
        return len(tensors) == len(self.refs) and all(
            r() is t and t._version == v for r, t, v in zip(self.refs, tensors, self.versions))


class MapCache:
    """Named LRU tables valid for one map/field state; `check(tensors, counters)` empties them all
    when either changed. `enabled=False` keeps nothing (the uncached baseline and its tests)."""

    def __init__(self, enabled: bool = True, sizes: dict[str, int] | None = None):
        self.enabled = enabled
        self.sizes = {"groups": 16, "renders": 8, "spacing": 1, "border": 1, "vocabulary": 1, "background": 8,
                      "graph": 1, "up": 1, **(sizes or {})}
        self.tables: dict[str, OrderedDict] = {k: OrderedDict() for k in self.sizes}
        self._tensors: TensorState | None = None
        self._counters: tuple | None = None
        self.hits = self.misses = self.invalidations = 0

    def check(self, tensors: tuple[torch.Tensor, ...], counters: tuple) -> None:
        if self._tensors is not None and self._counters == counters and self._tensors.same(tensors):
            return
        if any(self.tables.values()):
            self.invalidations += 1
        self.clear()
        self._tensors, self._counters = TensorState(tensors), counters

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
