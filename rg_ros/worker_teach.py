"""The map worker's teaching side (no rclpy here): teaching the object at a 3D point of the map (a
click in RViz) a name and forgetting one. Both change the live map, so they hold the map lock
(`_acquire`, ahead of the mapping thread) and the readers' lock (the models are shared with
queries), then publish a snapshot. The library does the work (rg_core/grounding/teach.py); on any
refusal it leaves the map as it was, and so do these. Point answers are reads (reads.py).
"""
from __future__ import annotations

import traceback

import numpy as np

from rg_core.grounding.result import GroundingResult

from .reads import EMPTY_MAP


class TeachWork:
    """Mixin of MapWorker: uses its mapper, lock (_acquire), read_lock, _publish, _ensure_grounder
    and log."""

    def _changing(self, timeout: float) -> bool:
        """Take the map lock, then the readers' lock (a query in progress finishes first)."""
        if not self._acquire(timeout):
            return False
        if self.read_lock.acquire(timeout=timeout if timeout > 0 else -1):
            return True
        self.lock.release()
        return False

    def _changed(self) -> None:
        """Publish what changed and release both locks."""
        try:
            self._publish()
        finally:
            self.read_lock.release()
            self.lock.release()

    def teach(self, name: str, point=None, result: GroundingResult | None = None,
              timeout: float = 30.0) -> tuple[GroundingResult, str, list[str]]:
        """Name the object at `point` [3] (map frame) or `result`'s first object `name`.
        -> (the answer the taught name gives now, or an unsuccessful result with the library's
        reason; the name as taught, "" on failure; every name the map holds after the call)."""
        from rg_core.grounding.teach import teach

        if not self.mapper.keyframes:
            return GroundingResult(False, f"cannot teach yet: {EMPTY_MAP}", query=str(name)[:200]), "", self.taught_names()
        if not self._changing(timeout):
            return (GroundingResult(False, f"map busy for {timeout:.1f} s (mapping); try again", query=str(name)[:200]),
                    "", self.taught_names())
        try:
            t, res = teach(self._ensure_grounder(), name, point=point, result=result)
            self._train_seconds, self._train_blocked = 0.0, ""   # the field trains on the new labels
            for o in res.objects if res.success else []:
                self.mapper.protect(o.aabb_min, o.aabb_max)
            return res, t.name, self.mapper.taught.names()
        except ValueError as exc:   # a bad name or point, nothing mapped there, a map not ready
            return GroundingResult(False, str(exc), query=str(name)[:200]), "", self.mapper.taught.names()
        except Exception as exc:  # noqa: BLE001
            self.log.error("teaching %r failed: %s\n%s", str(name)[:80], exc, traceback.format_exc())
            return (GroundingResult(False, f"teaching failed: {type(exc).__name__}: {exc}", query=str(name)[:200]),
                    "", self.mapper.taught.names())
        finally:
            self._changed()

    def forget(self, name: str, timeout: float = 30.0) -> tuple[bool, str, int, list[str]]:
        """Forget every object taught as `name` (or a spelling of it). -> (success, message,
        objects forgotten, every name the map holds after the call)."""
        from rg_core.grounding.teach import forget

        if not self._changing(timeout):
            return False, f"map busy for {timeout:.1f} s (mapping); try again", 0, self.taught_names()
        try:
            if not len(self.mapper.taught):   # nothing to relabel: the record set says what is wrong
                self.mapper.taught.forget(name)
            gone = forget(self._ensure_grounder(), name)
            self._train_seconds, self._train_blocked = 0.0, ""
            left = self.mapper.taught.names()
            where = "; ".join("({:.3f}, {:.3f}, {:.3f})".format(*np.asarray(t.point, float)) for t in gone)
            msg = (f"forgot {len(gone)} object{'s' if len(gone) != 1 else ''} taught as "
                   f"{', '.join(sorted({repr(t.name) for t in gone}))} at {where}; taught now: "
                   f"{', '.join(repr(n) for n in left) or 'nothing'}")
            return True, msg, len(gone), left
        except ValueError as exc:   # a bad name, nothing taught under it
            return False, str(exc), 0, self.mapper.taught.names()
        except Exception as exc:  # noqa: BLE001
            self.log.error("forgetting %r failed: %s\n%s", str(name)[:80], exc, traceback.format_exc())
            return False, f"forgetting failed: {type(exc).__name__}: {exc}", 0, self.mapper.taught.names()
        finally:
            self._changed()

    def taught_names(self) -> list[str]:
        """The names the map holds (no lock: a copy of a short list)."""
        return list(self.mapper.taught.names())
