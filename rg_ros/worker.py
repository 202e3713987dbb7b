"""The node's background mapping thread (no rclpy here: unit-testable without ROS).

Callbacks only convert messages and `submit()` frames into a bounded queue (`frame_queue.py`). One
worker thread takes frames out and runs `Mapper.add_frame` (a FrameError is logged and counted;
the map is untouched). When the queue is idle it does small slices of background work
(`idle_work.py`: supervision, field training, model loading, refinement).

One re-entrant lock (`MapWorker.lock`) is held around every map mutation and read that must see a
consistent map: add_frame, supervision, field training, refinement, reset, save, grounding, masks
and map snapshots. Callers go first: while one waits for the lock (`_acquire`), the thread starts
no new frame or slice and a training slice ends after its current step, so a query waits for at
most one frame, training step or supervision pass, not for every slice of a long background job
(a released lock is otherwise often re-taken by the thread that released it).
"""
from __future__ import annotations

import logging
import threading
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np

from rg_core.config import RGConfig
from rg_core.field.converge import describe
from rg_core.grounding.result import GroundingResult
from rg_core.perception.query import query_problem
from rg_core.map.frames import FrameError
from rg_core.map.mapper import Mapper

from .frame_queue import Frame, FrameQueue
from .idle_work import IdleWork
from .params import WorkerConfig
from .worker_teach import TeachWork

log = logging.getLogger("rg_ros.worker")


class MapWorker(TeachWork, IdleWork):
    """The mapping thread, its frame queue and the map lock; the services' side (reset, save,
    ground, scene graph, masks, snapshots, stats; point answers, teach and forget: worker_teach.py)."""

    def __init__(self, cfg: RGConfig | None = None, wcfg: WorkerConfig | None = None, mapper: Mapper | None = None,
                 logger: logging.Logger | None = None,
                 perception_loader: Callable[[], tuple[Any, Any]] | None = None):
        self.cfg = cfg or RGConfig()
        self.wcfg = wcfg or WorkerConfig()
        self.log = logger or log
        self.lock = threading.RLock()
        self._callers = 0                       # threads waiting in _acquire: the worker gives way
        self._callers_lock = threading.Lock()
        self._no_callers = threading.Event()
        self._no_callers.set()
        self.queue = FrameQueue(self.wcfg.queue_size)
        self.mapper = mapper if mapper is not None else Mapper(self.cfg.map)
        self.field = getattr(self.mapper, "field", None)
        self._grounder = None
        self._models_loaded = False   # the Grounder's models, loaded once the field first answers
        self._perception: tuple[Any, Any] | None = None   # (mask generator, embedder)
        self._perception_loader = perception_loader or self._load_perception
        self.perception_state = "off" if not self.wcfg.features else "not started"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loader: threading.Thread | None = None
        self.processed = 0
        self.rejected = 0
        self.last_error = ""
        self.last_result: dict = {}
        self.worker_error = ""
        self._train_seconds = 0.0        # since the last supervision change
        self._train_blocked = ""         # why training skipped (until supervision changes)
        self._supervised_count = 0
        self._refined_iters = 0           # since the last keyframe
        self._kf_count = len(self.mapper.keyframes)

    # ------------------------------------------------------------------------------ life cycle

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("worker already started")
        self._thread = threading.Thread(target=self._run, name="rg-map-worker", daemon=True)
        self._thread.start()
        if self.wcfg.features:
            self.perception_state = "loading"
            self._loader = threading.Thread(target=self._load_perception_thread, name="rg-perception-loader",
                                            daemon=True)
            self._loader.start()

    def stop(self, timeout: float | None = 30.0) -> bool:
        """Ask the thread to stop after its current step; returns True if it ended within `timeout`."""
        self._stop.set()
        self.queue.wake()
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, frame: Frame) -> bool:
        """Queue a frame (never blocks on mapping); True if the oldest queued frame was dropped."""
        return self.queue.put(frame)

    # ------------------------------------------------------------------------------ the thread

    def _run(self) -> None:
        try:
            busy = False
            while not self._stop.is_set():
                frame = self.queue.get(timeout=0 if busy else self.wcfg.idle_wait)
                while not self._no_callers.wait(0.1) and not self._stop.is_set():
                    pass                                # a caller waits for the lock: let it in first
                if self._stop.is_set():
                    break
                if frame is not None:
                    self._map_frame(frame)
                    busy = True
                    continue
                busy = self._idle_step()
        except Exception as exc:  # noqa: BLE001 - the node reports a dead worker in its status
            self.worker_error = f"{type(exc).__name__}: {exc}"
            self.log.error("mapping worker stopped: %s\n%s", self.worker_error, traceback.format_exc())

    def _map_frame(self, f: Frame) -> None:
        try:
            with self.lock:
                r = self.mapper.add_frame(f.rgb, f.depth, f.K, f.cam_to_world, f.stamp)
        except FrameError as exc:
            self.rejected += 1
            self.last_error = f"frame at {f.stamp:.3f} rejected: {exc}"
            self.log.warning("%s (map unchanged)", self.last_error)
            return
        self.processed += 1
        self.last_result = {"keyframe": r.keyframe, "reason": r.reason, "added": r.added,
                            "seconds": round(sum(r.seconds.values()), 3)}
        if r.keyframe:
            self._refined_iters = 0
            self.log.info("keyframe at %.3f (%d now): %s", f.stamp, len(self.mapper.keyframes), r.reason)

    # ------------------------------------------------------------------------------ services

    def reset(self) -> None:
        """Empty the map (and the queue: its frames count as dropped); perception models stay loaded.
        The frame counters live as long as the worker: mapped + rejected + dropped + queued = received."""
        self._acquire(0)
        try:
            self.queue.clear()
            self.mapper = Mapper(self.cfg.map)
            self.field, self._grounder = None, None
            self._train_seconds, self._train_blocked, self._supervised_count = 0.0, "", 0
            self._refined_iters = 0
            self.last_error, self.last_result = "", {}
        finally:
            self.lock.release()

    def save(self, path: str | Path) -> Path:
        from rg_core.map.store import save_map

        self._acquire(0)
        try:
            if self.field is not None and hasattr(self.field, "sync"):
                self.field.sync()   # the field follows Gaussians added or pruned since its last step
            return save_map(self.mapper, path)
        finally:
            self.lock.release()

    def caller_waits(self) -> bool:
        """A service call waits for the map lock: a training slice ends after its current step."""
        return not self._no_callers.is_set()

    def _acquire(self, timeout: float) -> bool:
        """Take the map lock ahead of the worker thread (it starts nothing new while a caller waits);
        timeout <= 0 waits as long as it takes. False: not acquired in time."""
        with self._callers_lock:
            self._callers += 1
            self._no_callers.clear()
        try:
            return self.lock.acquire(timeout=timeout if timeout > 0 else -1)
        finally:
            with self._callers_lock:
                self._callers -= 1
                if self._callers == 0:
                    self._no_callers.set()

    def ground(self, query: str, mode: str = "auto", max_results: int = 1, timeout: float = 30.0,
               cam_to_world: np.ndarray | None = None) -> GroundingResult:
        """Ground `query` in the current map; never raises (failures are unsuccessful results).
        `cam_to_world` [4, 4]: the camera of view-dependent words (None: the newest keyframe)."""
        problem = query_problem(query, self.cfg.ground.max_query_chars)
        if problem:
            return GroundingResult(False, problem, query=str(query)[:200])
        if not self.mapper.keyframes:
            return GroundingResult(False, "map is empty: no keyframes yet (send frames first)", query=query)
        if not self._acquire(timeout):
            return GroundingResult(False, f"map busy for {timeout:.1f} s (mapping); try again", query=query)
        try:
            res = self._ensure_grounder().ground(query, mode=mode, max_results=max_results, cam_to_world=cam_to_world,
                                                 camera="the robot's current camera")
            for o in res.objects if res.success else []:   # what was just grounded survives the map's budget
                self.mapper.protect(o.aabb_min, o.aabb_max)
            return res
        except ImportError as exc:   # a stage of the pipeline (reasoner, text encoder) has not landed
            self.log.error("grounding '%s': %s", query[:80], exc)
            return GroundingResult(False, f"grounding not available: {exc}", query=query)
        except Exception as exc:  # noqa: BLE001 - the service answers, the node lives
            self.log.error("grounding '%s' failed: %s\n%s", query[:80], exc, traceback.format_exc())
            return GroundingResult(False, f"grounding failed: {type(exc).__name__}: {exc}", query=query)
        finally:
            self.lock.release()

    def _ensure_grounder(self):
        """The Grounder over the current map (made on first use); call with the lock held."""
        from rg_core.field import FeatureField
        from rg_core.grounding.pipeline import Grounder

        if self.field is None:
            self.field = FeatureField(self.mapper, self.cfg.field)
        if self._grounder is None:
            text = self._perception[1].encode_texts if self._perception is not None else None  # the map's space
            self._grounder = Grounder.from_map(self.mapper, self.cfg, field=self.field, text_encoder=text)
        return self._grounder

    def scene_graph(self, timeout: float = 30.0) -> tuple[list, list, np.ndarray] | None:
        """(objects, relations, up) of the current map's scene graph (relations.build_graph, cached
        with the map), or None when the map is empty, not supervised yet or busy for `timeout` s.
        Never raises: a failure is logged and gives None."""
        if not self.mapper.keyframes or not self._acquire(timeout):
            return None
        try:
            from rg_core.grounding.relations import graph_relations

            g = self._ensure_grounder()
            if g._not_ready():
                return None
            objs, up = g.scene_graph(), g.up()
            return objs, graph_relations(objs, up), up
        except Exception as exc:  # noqa: BLE001 - the node lives
            self.log.error("scene graph failed: %s\n%s", exc, traceback.format_exc())
            return None
        finally:
            self.lock.release()

    def masks(self, result: GroundingResult, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
              timeout: float = 0.5, depth: np.ndarray | None = None,
              image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """(amodal, visible) bool [H, W] of a result from a camera (the visible one sharpened by that
        camera's depth image [H, W] metres and colour image [H, W, 3], if given), or None if the map
        is busy or there is no grounder (e.g. after a reset)."""
        if self._grounder is None or not self._acquire(timeout):
            return None
        try:
            if self._grounder is None:
                return None
            amodal, visible = self._grounder.masks(result, K, cam_to_world, width, height, depth, image)
            return np.asarray(amodal, bool), np.asarray(visible, bool)
        finally:
            self.lock.release()

    def snapshot(self, max_points: int = 0, timeout: float = 0.1) -> tuple[np.ndarray, np.ndarray] | None:
        """(Gaussian centres [N, 3] float32, colours [N, 3] uint8), evenly subsampled to
        `max_points` (0: all); None if the map is busy."""
        if not self._acquire(timeout):
            return None
        try:
            g = self.mapper.gaussians
            if not len(g):
                return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
            pts = g.means.detach().numpy().astype(np.float32)
            cols = (g.colors.detach().clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        finally:
            self.lock.release()
        if max_points and len(pts) > max_points:
            idx = np.linspace(0, len(pts) - 1, max_points).round().astype(np.int64)
            pts, cols = pts[idx], cols[idx]
        return pts, cols

    def stats(self) -> dict:
        """Counters for the status topic; takes no lock (never waits for mapping)."""
        m = self.mapper
        field = self.field
        return {"frames": m.frames_seen, "keyframes": len(m.keyframes), "gaussians": len(m.gaussians),
                "mapped": self.processed, "rejected": self.rejected, "queue": len(self.queue),
                "queue_size": self.queue.maxsize, "dropped": self.queue.dropped, "received": self.queue.put_count,
                "evicted": int(m.totals.get("evicted", 0)), "keyframes_dropped": int(m.totals.get("keyframes_dropped", 0)),
                "keyframes_replaced": int(m.totals.get("keyframes_replaced", 0)), "revisits": int(m.totals.get("revisits", 0)),
                "split": int(m.totals.get("split", 0)), "pruned": int(m.totals.get("pruned", 0)),
                "supervised_keyframes": self._supervised_count, "perception": self.perception_state,
                "field_steps": int(getattr(field, "steps", 0)) if field is not None else 0,
                "field_stop": describe(getattr(field, "stop", None)),
                "field_waits": self._train_blocked, "last_error": self.last_error,
                "worker": "running" if self.alive else ("stopped: " + self.worker_error if self.worker_error
                                                         else "stopped")}
