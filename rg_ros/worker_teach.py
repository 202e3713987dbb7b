"""The map worker's point and teaching side (no rclpy here): the object at a 3D point of the map
(a click in RViz), teaching it a name and forgetting one, serialised with mapping and /ground by
the worker's map lock (`_acquire`) like every other read of the map. The library does the work
(rg_core/grounding/point.py, teach.py); on any refusal it leaves the map as it was, and so do these.
"""
from __future__ import annotations

import traceback

import numpy as np

from rg_core.grounding.result import GroundingResult

EMPTY_MAP = "map is empty: no keyframes yet (send frames first)"


class TeachWork:
    """Mixin of MapWorker: uses its mapper, lock (_acquire), _ensure_grounder and log."""

    def point_answer(self, point, timeout: float = 30.0) -> GroundingResult:
        """The object at `point` [3] (map frame) as an answer (names, confidence, its group); never
        raises: bad input, nothing mapped there or a busy map is an unsuccessful result saying why."""
        from rg_core.grounding.point import point_answer

        where = "point"
        if not self.mapper.keyframes:
            return GroundingResult(False, EMPTY_MAP, query=where)
        if not self._acquire(timeout):
            return GroundingResult(False, f"map busy for {timeout:.1f} s (mapping); try again", query=where)
        try:
            res = point_answer(self._ensure_grounder(), point)
            for o in res.objects if res.success else []:   # what was just shown survives the map's budget
                self.mapper.protect(o.aabb_min, o.aabb_max)
            return res
        except Exception as exc:  # noqa: BLE001 - the caller gets an answer, the node lives
            self.log.error("point answer at %s failed: %s\n%s", point, exc, traceback.format_exc())
            return GroundingResult(False, f"point answer failed: {type(exc).__name__}: {exc}", query=where)
        finally:
            self.lock.release()

    def teach(self, name: str, point=None, result: GroundingResult | None = None,
              timeout: float = 30.0) -> tuple[GroundingResult, str, list[str]]:
        """Name the object at `point` [3] (map frame) or `result`'s first object `name`.
        -> (the answer the taught name gives now, or an unsuccessful result with the library's
        reason; the name as taught, "" on failure; every name the map holds after the call)."""
        from rg_core.grounding.teach import teach

        if not self.mapper.keyframes:
            return GroundingResult(False, f"cannot teach yet: {EMPTY_MAP}", query=str(name)[:200]), "", self.taught_names()
        if not self._acquire(timeout):
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
            self.lock.release()

    def forget(self, name: str, timeout: float = 30.0) -> tuple[bool, str, int, list[str]]:
        """Forget every object taught as `name` (or a spelling of it). -> (success, message,
        objects forgotten, every name the map holds after the call)."""
        from rg_core.grounding.teach import forget

        if not self._acquire(timeout):
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
            self.lock.release()

    def taught_names(self) -> list[str]:
        """The names the map holds (no lock: a copy of a short list)."""
        return list(self.mapper.taught.names())
