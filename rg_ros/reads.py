"""The map worker's read side (no rclpy here): /ground, point answers, answer masks, the scene graph
and the map cloud read the newest map snapshot (rg_core/map/snapshot.py), never the live map, so
they never wait for a frame, a supervision pass, a training slice or a save.

The mapping thread publishes a snapshot after each unit of work (`_publish`, with the map lock
held). Readers take `read_lock` among themselves only (one Grounder over the snapshots, whose
caches are not thread-safe) and record their latency (`latency`: diagnostics report p50, p95 and
max over the last minute).
"""
from __future__ import annotations

import threading
import time
import traceback
from collections import deque

import numpy as np
import torch

from rg_core.grounding.result import GroundingResult
from rg_core.map.snapshot import take_snapshot
from rg_core.perception.query import query_problem

EMPTY_MAP = "map is empty: no keyframes yet (send frames first)"


class LatencyWindow:
    """Durations (s) of the last `window` seconds: n, p50, p95 and max."""

    def __init__(self, window: float = 60.0):
        self.window = window
        self._items: deque[tuple[float, float]] = deque()
        self._lock = threading.Lock()

    def add(self, seconds: float, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._items.append((now, float(seconds)))
            self._trim(now)

    def _trim(self, now: float) -> None:
        while self._items and self._items[0][0] < now - self.window:
            self._items.popleft()

    def summary(self, now: float | None = None) -> dict:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._trim(now)
            d = np.array([s for _, s in self._items], float)
        if not len(d):
            return {"n": 0}
        return {"n": int(len(d)), "p50": round(float(np.percentile(d, 50)), 4),
                "p95": round(float(np.percentile(d, 95)), 4), "max": round(float(d.max()), 4)}


class MapReads:
    """Mixin of MapWorker: uses its cfg, mapper, field, lock, log, _perception and _ensure_grounder."""

    def _init_reads(self) -> None:
        self.read_lock = threading.Lock()
        self.latency = LatencyWindow(60.0)
        self._snap = None            # the newest snapshot (a Mapper sharing the live map's tensors)
        self._stale_since = None     # monotonic time the live map last moved past the snapshot, or None
        self._reader = None          # the Grounder queries run on (pointed at the newest snapshot)
        self.read_waited = 0.0       # s the latest read waited for another one
        self._asking = 0             # /ground and point answers in flight: the mapping thread starts no new unit
        self._asking_lock = threading.Lock()
        self._no_asking = threading.Event()
        self._no_asking.set()

    # ------------------------------------------------------------------------------ publishing

    def _publish(self, fresh: bool = False) -> None:
        """Make the live map's state the one readers see; call with the map lock held. `fresh`: a new
        map (load, reset), nothing of the old snapshot reused. Readers keep the old snapshot until
        the new one is assigned: never None in between (a query then said "map is empty")."""
        if self.field is not None and hasattr(self.field, "sync"):
            self.field.sync()   # the field follows Gaussians added or pruned since its last step
        self._snap = take_snapshot(self.mapper, None if fresh else self._snap)
        self._stale_since = None

    def _mark_stale(self) -> None:
        if self._stale_since is None:
            self._stale_since = time.monotonic()

    def snapshot_age(self) -> float:
        """Seconds the live map has been ahead of what readers see (0: they see it all)."""
        s = self._stale_since
        return 0.0 if s is None else max(0.0, time.monotonic() - s)

    def current(self):
        """The newest snapshot (made now if none was published yet and the map is free)."""
        snap = self._snap
        if snap is None and self.lock.acquire(blocking=False):
            try:
                self._publish()
                snap = self._snap
            finally:
                self.lock.release()
        return snap

    def _reader_for(self, snap):
        """The readers' Grounder over `snap`; call with read_lock held. Models are shared with the
        live map's Grounder (teaching), so each loads once."""
        from rg_core.grounding.pipeline import Grounder

        g = self._reader
        if g is None:
            text = self._perception[1].encode_texts if self._perception is not None else None
            g = self._reader = Grounder.from_map(snap, self.cfg, field=snap.field, text_encoder=text)
            self._share_models()
        g.mapper, g.field = snap, snap.field
        return g

    def _share_models(self) -> None:
        """The live map's Grounder and the readers' one use the same reasoner, text model and text
        cache (whichever has them loaded gives them to the other)."""
        a, b = self._grounder, self._reader
        if a is None or b is None:
            return
        for name in ("_reasoner", "_text"):
            if getattr(a, name) is None:
                setattr(a, name, getattr(b, name))
            else:
                setattr(b, name, getattr(a, name))
        b._text_cache = a._text_cache

    def _asked(self, delta: int) -> None:
        """Count a query in flight (+1) or done (-1). While one is, the mapping thread starts no new
        unit of work and a training slice ends after its step: the query has the CPU, yet waits for nothing."""
        with self._asking_lock:
            self._asking += delta
            (self._no_asking.set if self._asking == 0 else self._no_asking.clear)()

    def asking(self) -> bool:
        return not self._no_asking.is_set()

    def _give_way(self) -> None:
        """Inside a long unit of mapping work (between a supervision pass's keyframes): wait while
        a query runs (at most yield_to_queries s)."""
        self._no_asking.wait(self.wcfg.yield_to_queries)

    def _read(self, what: str, timeout: float):
        """(snapshot, grounder) with read_lock held, or (None, unsuccessful result) saying why."""
        snap = self.current()
        if snap is None or not snap.keyframes:
            return None, GroundingResult(False, EMPTY_MAP, query=what)
        t = time.perf_counter()
        if not self.read_lock.acquire(timeout=timeout if timeout > 0 else -1):
            return None, GroundingResult(False, f"another query held the map for {timeout:.1f} s; try again", query=what)
        self.read_waited = time.perf_counter() - t
        try:
            snap = self._snap or snap
            return snap, self._reader_for(snap)
        except BaseException:
            self.read_lock.release()
            raise

    def _protect(self, res: GroundingResult) -> None:
        """What was just answered survives the live map's budget (eviction)."""
        for o in res.objects if res.success else []:
            self.mapper.protect(o.aabb_min, o.aabb_max)

    # ------------------------------------------------------------------------------ reads

    def ground(self, query: str, mode: str = "auto", max_results: int = 1, timeout: float = 30.0,
               cam_to_world: np.ndarray | None = None) -> GroundingResult:
        """Ground `query` in the newest snapshot; never raises (failures are unsuccessful results).
        `cam_to_world` [4, 4]: the camera of view-dependent words (None: the newest keyframe)."""
        problem = query_problem(query, self.cfg.ground.max_query_chars)
        if problem:
            return GroundingResult(False, problem, query=str(query)[:200])
        self._asked(+1)
        try:
            return self._ground(query, mode, max_results, timeout, cam_to_world)
        finally:
            self._asked(-1)

    def _ground(self, query, mode, max_results, timeout, cam_to_world) -> GroundingResult:
        snap, g = self._read(query, timeout)
        if snap is None:
            return g
        try:
            t = time.perf_counter()
            res = g.ground(query, mode=mode, max_results=max_results, cam_to_world=cam_to_world,
                           camera="the robot's current camera")
            dt = time.perf_counter() - t
            if dt + self.read_waited > self.wcfg.slow_query:   # what a slow answer spent its time on
                self.log.warning("slow answer to '%s': %.2f s grounding (%s), %.2f s waiting for another read",
                                 query[:60], dt, ", ".join(f"{k} {v:.2f}" for k, v in res.timings.items()
                                                           if k != "field_training"), self.read_waited)
            self._protect(res)
            return res
        except ImportError as exc:   # a stage of the pipeline (reasoner, text encoder) has not landed
            self.log.error("grounding '%s': %s", query[:80], exc)
            return GroundingResult(False, f"grounding not available: {exc}", query=query)
        except Exception as exc:  # noqa: BLE001 - the service answers, the node lives
            self.log.error("grounding '%s' failed: %s\n%s", query[:80], exc, traceback.format_exc())
            return GroundingResult(False, f"grounding failed: {type(exc).__name__}: {exc}", query=query)
        finally:
            self.read_lock.release()

    def point_answer(self, point, timeout: float = 30.0) -> GroundingResult:
        """The object at `point` [3] (map frame) as an answer (names, confidence, its group); never
        raises: bad input, nothing mapped there or a busy map is an unsuccessful result saying why."""
        from rg_core.grounding.point import point_answer

        self._asked(+1)
        try:
            return self._point_answer(point_answer, point, timeout)
        finally:
            self._asked(-1)

    def _point_answer(self, point_answer, point, timeout: float) -> GroundingResult:
        snap, g = self._read("point", timeout)
        if snap is None:
            return g
        try:
            res = point_answer(g, point)
            self._protect(res)
            return res
        except Exception as exc:  # noqa: BLE001 - the caller gets an answer, the node lives
            self.log.error("point answer at %s failed: %s\n%s", point, exc, traceback.format_exc())
            return GroundingResult(False, f"point answer failed: {type(exc).__name__}: {exc}", query="point")
        finally:
            self.read_lock.release()

    def scene_graph(self, timeout: float = 30.0) -> tuple[list, list, np.ndarray] | None:
        """(objects, relations, up) of the newest snapshot's scene graph (relations.build_graph,
        cached with the map), or None when the map is empty, not supervised yet or another read
        held it for `timeout` s. Never raises: a failure is logged and gives None."""
        snap, g = self._read("scene graph", timeout)
        if snap is None:
            return None
        try:
            from rg_core.grounding.relations import graph_relations

            if g._not_ready():
                return None
            objs, up = g.scene_graph(), g.up()
            return objs, graph_relations(objs, up), up
        except Exception as exc:  # noqa: BLE001 - the node lives
            self.log.error("scene graph failed: %s\n%s", exc, traceback.format_exc())
            return None
        finally:
            self.read_lock.release()

    def masks(self, result: GroundingResult, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
              timeout: float = 0.05, depth: np.ndarray | None = None,
              image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """(amodal, visible) bool [H, W] of a result from a camera (the visible one sharpened by that
        camera's depth image [H, W] metres and colour image [H, W, 3], if given), or None when a query
        holds the reader for longer than `timeout` (the mask timer skips a beat, the query goes first)."""
        snap, g = self._read("masks", timeout)
        if snap is None:
            return None
        try:
            amodal, visible = g.masks(result, K, cam_to_world, width, height, depth, image)
            return np.asarray(amodal, bool), np.asarray(visible, bool)
        finally:
            self.read_lock.release()

    def snapshot(self, max_points: int = 0, timeout: float = 0.1) -> tuple[np.ndarray, np.ndarray] | None:
        """(Gaussian centres [N, 3] float32, colours [N, 3] uint8) of the newest snapshot, evenly
        subsampled to `max_points` (0: all); never waits (`timeout` is kept for callers)."""
        snap = self.current()
        if snap is None or not len(snap.gaussians):
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        g = snap.gaussians
        n = len(g)
        idx = np.linspace(0, n - 1, max_points).round().astype(np.int64) if max_points and n > max_points else None
        means, colors = (g.means, g.colors) if idx is None else (g.means[torch.from_numpy(idx)], g.colors[torch.from_numpy(idx)])
        pts = means.detach().numpy().astype(np.float32)
        cols = (colors.detach().clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        return pts, cols
