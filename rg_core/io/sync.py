"""Approximate time synchronisation of several topics (message_filters is not on PyPI); used by the
node (rg_ros) and by the rosbag2 reader (`rg map BAG`).

Simplified ApproximateTimeSynchronizer semantics, independent of rclpy so it is unit-testable:
each topic has a queue of at most `queue_size` messages kept sorted by stamp (out-of-order arrival
is fine). After every arrival the set with one message per topic and the smallest stamp spread is
found. It is emitted when its spread is <= `slop` seconds and no later arrival can pair it better:
its stamps are equal (spread 0), or every topic has already received a message at or after the
set's newest stamp (message_filters' ApproximateTime waits the same way; emitting the first set
within slop mixed frames whenever topics arrived out of step). The emitted messages and everything
older in their queues are removed. Messages pushed out of a full queue, passed over by an emitted
set, or older than the last emitted stamp of their topic are counted as dropped. `flush()` emits
what is left (the end of a bag).

A set never mixes frames: when messages are lost and the slop is as wide as the frame interval, the
closest set can pair one frame's colour with the next frame's depth and pose. Each topic's frame
interval is the lower quartile of its recent stamp gaps (the smallest of its first three); a member
more than MIX of its own interval away from the mean stamp of the others is out of place, and the
stale side (that member if older, the members older than it if newer) is dropped and counted in
`mixed`. Before a topic's first gaps are seen (the first frames) the check is weaker.
"""
from __future__ import annotations

import bisect
import collections
import itertools
import math
import threading
from typing import Any, Callable, Hashable, NamedTuple, Sequence


class SyncedSet(NamedTuple):
    stamps: tuple[float, ...]   # one per topic, in the order the topics were given
    msgs: tuple[Any, ...]
    spread: float               # max(stamps) - min(stamps), seconds


class ApproximateTimeSync:
    MIX = 0.6        # a member this many of its topic's frame intervals from the others' mean stamp is out of place
    GAPS = 16        # recent stamp gaps per topic behind its frame interval

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
            self._newest = [-math.inf] * len(self.topics)   # the newest stamp received per topic
            self._gaps = [collections.deque(maxlen=self.GAPS) for _ in self.topics]
            self._mixed = 0
            self._dropped = [0] * len(self.topics)
            self._emitted = 0

    @property
    def dropped(self) -> dict[Hashable, int]:
        with self._lock:
            return dict(zip(self.topics, self._dropped))

    @property
    def emitted(self) -> int:
        return self._emitted

    @property
    def mixed(self) -> int:
        """Sets refused because they would have mixed frames (their stale messages are dropped)."""
        return self._mixed

    def add(self, topic: Hashable, stamp: float, msg: Any) -> SyncedSet | None:
        """Queue one message; returns the newest synchronised set it completed (every one completed,
        oldest first, goes to the callback), None if none."""
        if topic not in self._index:
            raise KeyError(f"unknown topic {topic!r}; known: {list(self.topics)}")
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise ValueError(f"{topic}: stamp must be finite, got {stamp}")
        i = self._index[topic]
        with self._lock:
            out = self._add_locked(i, stamp, msg)
        if self.callback is not None:
            for s in out:
                self.callback(s)
        return out[-1] if out else None

    def flush(self) -> list[SyncedSet]:
        """Emit every set within slop that is left, final or not (no more messages will come)."""
        with self._lock:
            out = []
            while emitted := self._emit(final_only=False):
                out += emitted
        if self.callback is not None:
            for s in out:
                self.callback(s)
        return out

    def _add_locked(self, i: int, stamp: float, msg: Any) -> list[SyncedSet]:
        if self._last[i] is not None and stamp <= self._last[i]:   # a set at or after it already went out
            self._dropped[i] += 1
            return []
        q = self._queues[i]
        bisect.insort(q, (stamp, next(self._seq), msg))
        if stamp > self._newest[i]:
            if math.isfinite(self._newest[i]):
                self._gaps[i].append(stamp - self._newest[i])
            self._newest[i] = stamp
        if len(q) > self.queue_size:
            q.pop(0)
            self._dropped[i] += 1
        return self._emit(final_only=True)

    def _emit(self, final_only: bool) -> list[SyncedSet]:
        """Take the ready sets out of the queues, oldest first: the closest set if it is final (or
        `final_only` is off) and, before it, the ready sets among the messages older than its own.
        A ready set that would mix frames drops its stale messages instead, and the search starts over."""
        out = []
        while True:
            chain = self._ready(list(map(len, self._queues)), final_only)
            for spread, members in chain:
                stale, mixed = self._stale(members)
                if stale:
                    for k in stale:
                        self._queues[k].remove(members[k])
                        self._dropped[k] += 1
                    self._mixed += mixed
                    break
                for k, m in enumerate(members):
                    qk = self._queues[k]
                    j = next(n for n, e in enumerate(qk) if e[1] == m[1])
                    self._dropped[k] += j   # older messages passed over by this set
                    del qk[: j + 1]
                    self._last[k] = m[0]
                self._emitted += 1
                out.append(SyncedSet(tuple(m[0] for m in members), tuple(m[2] for m in members), spread))
            else:
                return out

    def _interval(self, k: int) -> float | None:
        """Topic k's frame interval: the lower quartile of its recent stamp gaps (a lost message
        doubles a gap), their smallest while there are fewer than 4; None before the first gap."""
        g = sorted(self._gaps[k])
        return None if not g else g[(len(g) - 1) // 4] if len(g) >= 4 else g[0]

    def _stale(self, members: list[tuple]) -> tuple[list[int], bool]:
        """(topics whose member of this set is stale, whether the set would have mixed frames):
        ([], False) if none is. A stale member with a message of its own topic queued nearer to the
        others (a faster topic: another of its messages fits better) is passed over, not a mix."""
        t = [m[0] for m in members]
        n = len(t)
        out, mixed = set(), False
        for k in range(n):
            p = self._interval(k)
            mean = (sum(t) - t[k]) / (n - 1)
            d = t[k] - mean
            if p is None or abs(d) <= self.MIX * p:
                continue
            if d < 0:                 # older than its partners: its own partners were lost, or a later one fits
                out.add(k)
                mixed |= not any(abs(e[0] - mean) < abs(d) for e in self._queues[k] if e[0] > t[k])
            else:                     # newer: the partners are of an older frame whose message k was lost
                old = {j for j in range(n) if t[j] < t[k] - self.MIX * (self._interval(j) or p)}
                out |= old
                mixed |= bool(old)
        return sorted(out), mixed

    def _ready(self, ends: list[int], final_only: bool) -> list[tuple[float, list[tuple]]]:
        best = self._closest_set(ends)
        if best is None or best[0] > self.slop:
            return []
        spread, picks = best
        members = [q[j] for q, j in zip(self._queues, picks)]
        older = self._ready(picks, final_only)   # the messages before this set, each topic
        newest = max(m[0] for m in members)
        if final_only and spread > 0 and any(n < newest for n in self._newest):
            return older   # a topic's partner may still come and pair better
        return older + [(spread, members)]

    def _closest_set(self, ends: list[int]) -> tuple[float, list[int]] | None:
        """(spread, index per queue) of the set with the smallest stamp spread, earliest on ties,
        among the first ends[k] messages of each queue k.

        Each such message is tried as the set's earliest member; every other queue then
        contributes its first message at or after it (any later one only widens the spread)."""
        if any(e == 0 for e in ends):
            return None
        stamps = [[e[0] for e in q[:n]] for q, n in zip(self._queues, ends)]
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
