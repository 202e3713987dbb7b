"""Approximate time synchronisation of several topics (message_filters is not on PyPI); used by the
node (rg_ros) and by the rosbag2 reader (`rg map BAG`).

Simplified ApproximateTimeSynchronizer semantics, independent of rclpy so it is unit-testable:
each topic has a queue of at most `queue_size` messages kept sorted by stamp (out-of-order arrival
is fine). After every arrival the set with one message per topic and the smallest stamp spread is
found; if that spread is <= `slop` seconds it is emitted at once, and the emitted messages and
everything older in their queues are removed. Messages pushed out of a full queue, passed over by
an emitted set, or older than the last emitted stamp of their topic are counted as dropped.
"""
from __future__ import annotations

import bisect
import itertools
import math
import threading
from typing import Any, Callable, Hashable, NamedTuple, Sequence


class SyncedSet(NamedTuple):
    stamps: tuple[float, ...]   # one per topic, in the order the topics were given
    msgs: tuple[Any, ...]
    spread: float               # max(stamps) - min(stamps), seconds


class ApproximateTimeSync:
    def __init__(self, topics: Sequence[Hashable], queue_size: int = 10, slop: float = 0.05,
                 callback: Callable[[SyncedSet], None] | None = None):
        if len(topics) < 2 or len(set(topics)) != len(topics):
            raise ValueError(f"need at least two distinct topics, got {list(topics)}")
        if queue_size < 1 or not (slop >= 0 and math.isfinite(slop)):
            raise ValueError(f"need queue_size >= 1 and finite slop >= 0, got {queue_size}, {slop}")
        self.topics = tuple(topics)
        self.queue_size, self.slop, self.callback = int(queue_size), float(slop), callback
        self._index = {t: i for i, t in enumerate(self.topics)}
        self._lock = threading.Lock()
        self._seq = itertools.count()   # tie-breaker so equal stamps never compare messages
        self.reset()

    def reset(self) -> None:
        with self._lock:
            self._queues: list[list[tuple[float, int, Any]]] = [[] for _ in self.topics]   # sorted by stamp
            self._last: list[float | None] = [None] * len(self.topics)
            self._dropped = [0] * len(self.topics)
            self._emitted = 0

    @property
    def dropped(self) -> dict[Hashable, int]:
        with self._lock:
            return dict(zip(self.topics, self._dropped))

    @property
    def emitted(self) -> int:
        return self._emitted

    def add(self, topic: Hashable, stamp: float, msg: Any) -> SyncedSet | None:
        """Queue one message; returns (and passes to the callback) a synchronised set if one is ready."""
        if topic not in self._index:
            raise KeyError(f"unknown topic {topic!r}; known: {list(self.topics)}")
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise ValueError(f"{topic}: stamp must be finite, got {stamp}")
        i = self._index[topic]
        with self._lock:
            out = self._add_locked(i, stamp, msg)
        if out is not None and self.callback is not None:
            self.callback(out)
        return out

    def _add_locked(self, i: int, stamp: float, msg: Any) -> SyncedSet | None:
        if self._last[i] is not None and stamp <= self._last[i]:   # a set at or after it already went out
            self._dropped[i] += 1
            return None
        q = self._queues[i]
        bisect.insort(q, (stamp, next(self._seq), msg))
        if len(q) > self.queue_size:
            q.pop(0)
            self._dropped[i] += 1
        best = self._closest_set()
        if best is None or best[0] > self.slop:
            return None
        spread, picks = best
        chosen = []
        for k, j in enumerate(picks):
            qk = self._queues[k]
            chosen.append(qk[j])
            self._dropped[k] += j   # older messages passed over by this set
            del qk[: j + 1]
            self._last[k] = chosen[-1][0]
        self._emitted += 1
        return SyncedSet(tuple(c[0] for c in chosen), tuple(c[2] for c in chosen), spread)

    def _closest_set(self) -> tuple[float, list[int]] | None:
        """(spread, index per queue) of the set with the smallest stamp spread, earliest on ties.

        Each queued message is tried as the set's earliest member; every other queue then
        contributes its first message at or after it (any later one only widens the spread)."""
        if any(not q for q in self._queues):
            return None
        stamps = [[e[0] for e in q] for q in self._queues]
        best: tuple[float, list[int]] | None = None
        for k, sk in enumerate(stamps):
            for j, t0 in enumerate(sk):
                picks, hi = [], t0
                for m, sm in enumerate(stamps):
                    idx = j if m == k else bisect.bisect_left(sm, t0)
                    if idx == len(sm):
                        break
                    picks.append(idx)
                    hi = max(hi, sm[idx])
                else:
                    cand = (hi - t0, picks)
                    if best is None or cand[0] < best[0] or (cand[0] == best[0] and t0 < self._min_of(best[1], stamps)):
                        best = cand
        return best

    @staticmethod
    def _min_of(picks: list[int], stamps: list[list[float]]) -> float:
        return min(s[p] for s, p in zip(stamps, picks))
