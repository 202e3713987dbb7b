"""The node's background mapping thread (no rclpy here: unit-testable without ROS).

Callbacks only convert messages and `submit()` frames into a bounded queue (`frame_queue.py`). One
worker thread takes frames out and runs `Mapper.add_frame` (a FrameError is logged and counted;
the map is untouched). When the queue is idle it does small slices of background work
(`idle_work.py`: supervision, field training, model loading, refinement).

Readers never touch the live map: after each unit of work the thread publishes a snapshot
(rg_core/map/snapshot.py) and /ground, point answers, masks, the scene graph, the map cloud and
saves read that (`reads.py`, `map_admin.py`), so a query never waits for mapping work.
One re-entrant lock (`MapWorker.lock`) is held around every change of the live map: add_frame,
supervision, field training, refinement, teaching, reset and loading. Callers that change the map
go first: while one waits for the lock (`_acquire`), the thread starts no new frame or slice and a
training slice ends after its current step.
"""
from __future__ import annotations

import logging
import os
import threading
import traceback
from typing import Any, Callable

from rg_core.config import RGConfig
from rg_core.field.converge import describe
from rg_core.map.frames import FrameError
from rg_core.map.mapper import Mapper

from .frame_queue import Frame, FrameQueue
from .idle_work import IdleWork
from .map_admin import MapAdmin
from .params import WorkerConfig
from .reads import MapReads
from .worker_teach import TeachWork

log = logging.getLogger("rg_ros.worker")


class MapWorker(MapReads, MapAdmin, TeachWork, IdleWork):
    """The mapping thread, its frame queue and the map lock; the services' side (reset, stats;
    reads of the newest snapshot: reads.py; save, load, pause: map_admin.py; teach and forget:
    worker_teach.py)."""

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
        self._init_reads()
        self._init_admin()
        with self.lock:
            self._publish()   # a start-up map answers from the first query on

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
        """Queue a frame (never blocks on mapping); True if the oldest queued frame was dropped.
        While mapping is paused the frame is counted and dropped (False)."""
        if self.paused:
            self.paused_dropped += 1
            return False
        return self.queue.put(frame)

    # ------------------------------------------------------------------------------ the thread

    def _run(self) -> None:
        try:   # mapping runs at a lower CPU priority than the callbacks and queries (Linux: per thread)
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.wcfg.mapping_nice)
        except (AttributeError, OSError, PermissionError):
            pass
        try:
            busy = False
            while not self._stop.is_set():
                frame = self.queue.get(timeout=0 if busy else self.wcfg.idle_wait)
                while not self._no_callers.wait(0.1) and not self._stop.is_set():
                    pass                                # a caller waits for the lock: let it in first
                self._give_way()                        # a query runs: let it have the CPU
                if self._stop.is_set():
                    break
                if frame is not None:
                    self._map_frame(frame)
                    busy = True
                    continue
                if self.paused:   # the map does not change: no supervision, training or refinement
                    busy = False
                    continue
                self._mark_stale()
                busy = self._idle_step()
                with self.lock:   # what the step changed (or nothing: the same snapshot again)
                    self._publish()
        except Exception as exc:  # noqa: BLE001 - the node reports a dead worker in its status
            self.worker_error = f"{type(exc).__name__}: {exc}"
            self.log.error("mapping worker stopped: %s\n%s", self.worker_error, traceback.format_exc())

    def _map_frame(self, f: Frame) -> None:
        self._mark_stale()
        try:
            with self.lock:
                try:
                    r = self.mapper.add_frame(f.rgb, f.depth, f.K, f.cam_to_world, f.stamp)
                finally:
                    self._publish()   # before the counters: a frame counted as mapped is in the snapshot
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
            self._publish(fresh=True)
        finally:
            self.lock.release()

    def caller_waits(self) -> bool:
        """A service call waits for the map lock, or a query runs: a training slice ends after its
        current step."""
        return not self._no_callers.is_set() or self.asking()

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

    def _ensure_grounder(self):
        """The Grounder over the current map (made on first use); call with the lock held."""
        from rg_core.field import FeatureField
        from rg_core.grounding.pipeline import Grounder

        if self.field is None:
            self.field = FeatureField(self.mapper, self.cfg.field)
        if self._grounder is None:
            text = self._perception[1].encode_texts if self._perception is not None else None  # the map's space
            self._grounder = Grounder.from_map(self.mapper, self.cfg, field=self.field, text_encoder=text)
            self._share_models()
        return self._grounder

    def stats(self) -> dict:
        """Counters for the status topic; takes no lock (never waits for mapping). Keyframes,
        Gaussians and the field's steps and stop are the newest snapshot's (what a query answers
        from: a status that says the field answers means a query gets an answer)."""
        m = self.mapper
        snap = self._snap if self._snap is not None else m   # what queries see
        field = snap.field if self._snap is not None else self.field
        return {"frames": m.frames_seen, "keyframes": len(snap.keyframes), "gaussians": len(snap.gaussians),
                "mapped": self.processed, "rejected": self.rejected, "queue": len(self.queue),
                "queue_size": self.queue.maxsize, "dropped": self.queue.dropped + self.paused_dropped,
                "received": self.queue.put_count + self.paused_dropped, "dropped_paused": self.paused_dropped,
                "paused": self.paused, "saving": self.saving, "saves": self.saves,
                "snapshot_age_s": round(self.snapshot_age(), 3), "query_latency_s": self.latency.summary(),
                "evicted": int(m.totals.get("evicted", 0)), "keyframes_dropped": int(m.totals.get("keyframes_dropped", 0)),
                "keyframes_replaced": int(m.totals.get("keyframes_replaced", 0)), "revisits": int(m.totals.get("revisits", 0)),
                "split": int(m.totals.get("split", 0)), "pruned": int(m.totals.get("pruned", 0)),
                "supervised_keyframes": (len(snap.supervision.by_keyframe) if self._snap is not None and snap.supervision
                                         is not None else self._supervised_count), "perception": self.perception_state,
                "grounding_models": "loaded" if self._models_loaded else "not loaded",
                "field_steps": int(getattr(field, "steps", 0)) if field is not None else 0,
                "field_stop": describe(getattr(field, "stop", None)),
                "field_waits": self._train_blocked, "last_error": self.last_error,
                "worker": "running" if self.alive else ("stopped: " + self.worker_error if self.worker_error
                                                         else "stopped")}
