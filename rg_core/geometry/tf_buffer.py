"""A transform buffer with tf2's semantics, in numpy (tf2_ros is not on PyPI; `rg map BAG` needs
the same lookups headless). rg_ros only converts tf2_msgs/TFMessage into `set_transform` calls.

What follows tf2 (BufferCore):
- each child frame has one parent at a time; a transform parent <- child maps points in the child
  frame into the parent frame;
- static transforms hold at all times; dynamic ones are kept for `cache_time` seconds behind the
  newest sample of their link and interpolated at the requested stamp (translation linearly,
  rotation by slerp); a stamp outside a link's samples is an extrapolation error (tf2 allows none;
  `extrapolation_limit` lets a lookup use the nearest sample that close);
- a lookup chains through any number of frames via the common ancestor; time 0 (or None) means
  the latest time all links of the chain have in common;
- errors name the frames and times (ConnectivityError, ExtrapolationError, LoopError); bad input
  (NaN, a non-unit quaternion, a frame that is its own parent, an empty frame id) is refused with
  an error and leaves the buffer as it was.

One deliberate extra: `max_gap` > 0 refuses to interpolate a dynamic link across two samples
further apart than that (tf2 interpolates across any gap, so an odometry dropout would hand
frames invented poses); 0 keeps tf2's behaviour.
"""
from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass

import numpy as np

from .rotations import quat_to_rot

QUAT_NORM_TOL = 1e-2   # tf2 refuses quaternions whose squared norm is off by more than 0.01 (denormalized)
MAX_DEPTH = 1000       # tf2's MAX_GRAPH_DEPTH: a longer walk up the tree is a loop


class TFError(ValueError):
    """A transform could not be stored or looked up; the message says which frames and times."""


class ConnectivityError(TFError):
    """The two frames are not connected (a link is missing)."""


class ExtrapolationError(TFError):
    """The requested time is outside the samples of a link (or inside a gap wider than max_gap)."""


class PastExtrapolationError(ExtrapolationError):
    """The requested time is older than a link's oldest sample: waiting cannot cure it."""


class GapError(ExtrapolationError):
    """The requested time falls between two samples further apart than max_gap: waiting cannot cure it."""


class LoopError(TFError):
    """The frames' parent links form a cycle."""


class InvalidTransformError(TFError):
    """NaN/inf values, a non-unit quaternion, empty or equal frame ids."""


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions [x, y, z, w] (shortest arc), a in [0, 1]."""
    d = float(np.dot(q0, q1))
    if d < 0.0:   # q and -q are the same rotation: take the short way round
        q1, d = -q1, -d
    if d > 0.9995:   # nearly equal: normalised lerp avoids dividing by sin(~0)
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(d, 1.0))
    s = math.sin(theta)
    return (math.sin((1 - a) * theta) / s) * q0 + (math.sin(a * theta) / s) * q1


def to_matrix(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """translation [3] + quaternion [x, y, z, w] -> [4, 4]."""
    T = np.eye(4)
    T[:3, :3] = quat_to_rot(q)
    T[:3, 3] = t
    return T


@dataclass(frozen=True)
class _Sample:
    stamp: float
    parent: str
    t: np.ndarray   # [3]
    q: np.ndarray   # [4] x, y, z, w (unit)


class TFBuffer:
    """Thread-safe transform buffer (see the module docstring for the semantics)."""

    def __init__(self, cache_time: float = 10.0, extrapolation_limit: float = 0.0, max_gap: float = 0.0):
        for name, v in (("cache_time", cache_time), ("extrapolation_limit", extrapolation_limit), ("max_gap", max_gap)):
            if not (v >= 0):
                raise ValueError(f"TFBuffer: {name} must be >= 0, got {v}")
        self.cache_time = float(cache_time)
        self.extrapolation_limit = float(extrapolation_limit)
        self.max_gap = float(max_gap)
        self._lock = threading.RLock()
        self._static: dict[str, _Sample] = {}            # child -> sample (stamp ignored)
        self._dynamic: dict[str, list[_Sample]] = {}     # child -> samples sorted by stamp
        self._stamps: dict[str, list[float]] = {}        # child -> their stamps (for bisect)
        self.rejected = 0

    # ------------------------------------------------------------------------------ input

    def set_transform(self, parent: str, child: str, stamp: float, translation, rotation, static: bool = False) -> None:
        """Store parent <- child at `stamp` (seconds). translation [3], rotation quaternion [x, y, z, w].

        Raises InvalidTransformError (bad numbers or frame ids), LoopError (the link would close a
        cycle at the newest time) or ExtrapolationError (older than the cache keeps); the buffer is
        unchanged then."""
        try:
            self._set(parent, child, stamp, translation, rotation, static)
        except TFError:
            self.rejected += 1
            raise

    def _set(self, parent, child, stamp, translation, rotation, static):
        parent, child = _strip(parent), _strip(child)
        what = f"transform '{parent}' <- '{child}'"
        if not parent or not child:
            raise InvalidTransformError(f"{what}: frame ids must not be empty")
        if parent == child:
            raise InvalidTransformError(f"{what}: a frame cannot be its own parent")
        t = np.asarray(translation, dtype=np.float64).reshape(3)
        q = np.asarray(rotation, dtype=np.float64).reshape(4)
        stamp = float(stamp)
        if not (np.isfinite(t).all() and np.isfinite(q).all() and math.isfinite(stamp)):
            raise InvalidTransformError(f"{what} at t={stamp}: NaN or inf in translation {t.tolist()}, "
                                        f"rotation {q.tolist()} or stamp")
        n2 = float(q @ q)
        if abs(n2 - 1.0) > QUAT_NORM_TOL:
            raise InvalidTransformError(f"{what} at t={stamp:.9f}: quaternion {q.tolist()} is not normalised "
                                        f"(norm {math.sqrt(n2):.4g})")
        q = q / math.sqrt(n2)
        with self._lock:
            cyc = self._cycle_through(parent, child)
            if cyc:
                raise LoopError(f"{what}: would close a loop in the tree: {' -> '.join(cyc)}")
            s = _Sample(stamp, parent, t, q)
            if static:
                self._static[child] = s
                return
            stamps = self._stamps.setdefault(child, [])
            samples = self._dynamic.setdefault(child, [])
            if stamps and stamp < stamps[-1] - self.cache_time:
                if not samples:
                    del self._stamps[child], self._dynamic[child]
                raise ExtrapolationError(f"{what} at t={stamp:.9f}: older than the buffer keeps (newest "
                                         f"{stamps[-1]:.9f}, cache {self.cache_time:g} s); ignored (TF_OLD_DATA)")
            i = bisect.bisect_left(stamps, stamp)
            if i < len(stamps) and stamps[i] == stamp:   # same stamp again: the newer message wins
                samples[i] = s
            else:
                stamps.insert(i, stamp)
                samples.insert(i, s)
            cut = bisect.bisect_left(stamps, stamps[-1] - self.cache_time)
            if cut:
                del stamps[:cut], samples[:cut]

    def _latest_parent(self, frame: str) -> str | None:
        if frame in self._dynamic and self._dynamic[frame]:
            return self._dynamic[frame][-1].parent
        if frame in self._static:
            return self._static[frame].parent
        return None

    def _cycle_through(self, parent: str, child: str) -> list[str] | None:
        """The cycle that parent <- child would close with the newest links, or None."""
        chain, f = [child, parent], parent
        for _ in range(MAX_DEPTH):
            f = self._latest_parent(f)
            if f is None:
                return None
            chain.append(f)
            if f == child:
                return chain
        return chain[:6] + ["..."]

    def clear(self) -> None:
        with self._lock:
            self._static.clear()
            self._dynamic.clear()
            self._stamps.clear()

    # ------------------------------------------------------------------------------ queries

    @property
    def frames(self) -> set[str]:
        with self._lock:
            out = set(self._static) | {c for c, s in self._dynamic.items() if s}
            out |= {s.parent for s in self._static.values()}
            out |= {s.parent for v in self._dynamic.values() for s in v}
            return out

    def lookup(self, target: str, source: str, stamp: float | None = None) -> np.ndarray:
        """target <- source at `stamp` as [4, 4] (maps points in `source` into `target`), tf2's
        lookupTransform(target_frame, source_frame, time). None or 0 = the latest common time."""
        target, source = _strip(target), _strip(source)
        with self._lock:
            if stamp is None or stamp == 0:
                stamp = self._latest_common_time(target, source)
            return self._lookup(target, source, float(stamp))

    def can_transform(self, target: str, source: str, stamp: float | None = None) -> tuple[bool, str]:
        """(True, "") or (False, why)."""
        try:
            self.lookup(target, source, stamp)
            return True, ""
        except TFError as exc:
            return False, str(exc)

    def _ancestors(self, frame: str, stamp: float | None) -> list[str]:
        """frame, its parent, ... up to the root at `stamp` (None: newest links). LoopError on a cycle."""
        chain, seen, f = [frame], {frame}, frame
        while True:
            p = self._parent_at(f, stamp)
            if p is None:
                return chain
            if p in seen or len(chain) > MAX_DEPTH:
                cyc = chain[chain.index(p):] + [p] if p in seen else chain[-5:]
                raise LoopError(f"the tf tree contains a loop: {' -> '.join(cyc)} (looking up from '{frame}')")
            chain.append(p)
            seen.add(p)
            f = p

    def _parent_at(self, frame: str, stamp: float | None) -> str | None:
        samples = self._dynamic.get(frame)
        if samples:
            if stamp is None:
                return samples[-1].parent
            i = bisect.bisect_right(self._stamps[frame], stamp)
            return samples[max(i - 1, 0)].parent   # the sample at or before the stamp (or the first)
        s = self._static.get(frame)
        return s.parent if s is not None else None

    def _path(self, target: str, source: str, stamp: float | None) -> tuple[list[str], list[str]]:
        """(source up to the common ancestor, target up to it), both starting at their own frame."""
        known = self.frames
        for f, role in ((source, "source"), (target, "target")):
            if f not in known:
                raise ConnectivityError(f"\"{f}\" passed to lookup ({role} frame) does not exist; known frames: "
                                        f"{', '.join(sorted(known)) or 'none'}")
        up_s = self._ancestors(source, stamp)
        up_t = self._ancestors(target, stamp)
        common = next((f for f in up_s if f in set(up_t)), None)
        if common is None:
            raise ConnectivityError(f"could not find a connection between '{target}' and '{source}' because they "
                                    f"are not part of the same tree (roots '{up_t[-1]}' and '{up_s[-1]}'); "
                                    f"a link is missing")
        return up_s[: up_s.index(common) + 1], up_t[: up_t.index(common) + 1]

    def _latest_common_time(self, target: str, source: str) -> float:
        if target == source:
            return 0.0
        a, b = self._path(target, source, None)
        newest = [self._stamps[f][-1] for f in a[:-1] + b[:-1] if self._dynamic.get(f)]
        return min(newest) if newest else 0.0

    def _link(self, child: str, stamp: float, target: str, source: str) -> tuple[np.ndarray, np.ndarray]:
        """(t, q) of parent <- child at `stamp`, interpolated."""
        samples = self._dynamic.get(child)
        if not samples:
            s = self._static[child]
            return s.t, s.q
        stamps = self._stamps[child]
        lo, hi = stamps[0], stamps[-1]
        ctx = f"when looking up transform from frame [{source}] to frame [{target}] (link '{samples[-1].parent}' " \
              f"<- '{child}')"
        if stamp < lo:
            if lo - stamp <= self.extrapolation_limit:
                return samples[0].t, samples[0].q
            raise PastExtrapolationError(f"Lookup would require extrapolation into the past. Requested time {stamp:.9f} "
                                     f"but the earliest data is at time {lo:.9f}, {ctx}")
        if stamp > hi:
            if stamp - hi <= self.extrapolation_limit:
                return samples[-1].t, samples[-1].q
            raise ExtrapolationError(f"Lookup would require extrapolation into the future. Requested time "
                                     f"{stamp:.9f} but the latest data is at time {hi:.9f}, {ctx}")
        i = bisect.bisect_left(stamps, stamp)
        if stamps[i] == stamp:
            return samples[i].t, samples[i].q
        s0, s1 = samples[i - 1], samples[i]
        if self.max_gap > 0 and s1.stamp - s0.stamp > self.max_gap:
            raise GapError(f"Lookup at time {stamp:.9f} falls in a gap of {s1.stamp - s0.stamp:.3f} s "
                                     f"between samples at {s0.stamp:.9f} and {s1.stamp:.9f} (max_gap "
                                     f"{self.max_gap:g} s), {ctx}")
        if s0.parent != s1.parent:   # reparented between the samples: tf2 uses the earlier one
            return s0.t, s0.q
        a = (stamp - s0.stamp) / (s1.stamp - s0.stamp)
        return s0.t + a * (s1.t - s0.t), slerp(s0.q, s1.q, a)

    def _lookup(self, target: str, source: str, stamp: float) -> np.ndarray:
        if target == source:
            if target not in self.frames:
                raise ConnectivityError(f"\"{target}\" passed to lookup does not exist")
            return np.eye(4)
        up_s, up_t = self._path(target, source, stamp)
        # common <- source = product of the links walking up from source; same for target.
        T_cs = np.eye(4)
        for f in up_s[:-1]:
            T_cs = to_matrix(*self._link(f, stamp, target, source)) @ T_cs
        T_ct = np.eye(4)
        for f in up_t[:-1]:
            T_ct = to_matrix(*self._link(f, stamp, target, source)) @ T_ct
        return _inv(T_ct) @ T_cs


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def _strip(frame: str) -> str:
    """tf2 ignores a leading slash (tf1 style '/map')."""
    return str(frame).lstrip("/")
