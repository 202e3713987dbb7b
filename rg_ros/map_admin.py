"""The map worker's map-server side (no rclpy here): saving from a snapshot in the background,
loading a map file in place of the current map, pausing and resuming mapping.

- A save writes the newest snapshot (rg_core/map/snapshot.py) with store.save_map (a temp file, then
  a rename) in its own thread: mapping and queries go on. One save at a time: a second one while it
  runs is refused with what is being saved (`SaveBusy`).
- A load reads the file outside every lock (queries are answered from the old map meanwhile), then
  swaps the map in one step under the map lock and publishes its snapshot.
- While paused, frames are counted (`paused_dropped`) and dropped, the map does not change (no
  mapping, supervision, training or refinement), and queries are answered.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path


class SaveBusy(RuntimeError):
    """A save was asked for while another one runs."""


class SaveJob:
    """One background save: `wait()` -> the path written, or raises what the save raised."""

    def __init__(self, path: Path, snap, write):
        self.path, self.started = path, time.monotonic()
        self._done = threading.Event()
        self._out: Path | None = None
        self._error: BaseException | None = None
        self.gaussians, self.keyframes = len(snap.gaussians), len(snap.keyframes)
        self._thread = threading.Thread(target=self._run, args=(snap, write), name="rg-map-save", daemon=True)
        self._thread.start()

    def _run(self, snap, write) -> None:
        try:
            self._out = write(snap, self.path)
        except BaseException as exc:  # noqa: BLE001 - handed to whoever waits
            self._error = exc
        finally:
            self._done.set()

    @property
    def running(self) -> bool:
        return not self._done.is_set()

    def wait(self, timeout: float | None = None) -> Path:
        if not self._done.wait(timeout):
            raise TimeoutError(f"saving {self.path} still runs after {timeout:.0f} s")
        if self._error is not None:
            raise self._error
        return self._out


class MapAdmin:
    """Mixin of MapWorker: uses its cfg, mapper, lock, _acquire, queue, _publish and current()."""

    def _init_admin(self) -> None:
        self._save_job: SaveJob | None = None
        self._save_lock = threading.Lock()
        self._paused = threading.Event()
        self.paused_dropped = 0
        self.saves = 0

    # ------------------------------------------------------------------------------ saving

    def save_async(self, path: str | Path, write=None) -> SaveJob:
        """Start writing the newest snapshot to `path`; SaveBusy if a save runs. `write(snap, path)`
        defaults to store.save_map (tests pass one that blocks on an event)."""
        from rg_core.map.store import save_map

        path = Path(path).expanduser()
        with self._save_lock:
            job = self._save_job
            if job is not None and job.running:
                raise SaveBusy(f"already saving {job.path} (started {time.monotonic() - job.started:.1f} s ago); "
                               "this save was not started")
            snap = self._fresh_snapshot()
            self._save_job = SaveJob(path, snap, write or save_map)
            self.saves += 1
            return self._save_job

    def save(self, path: str | Path, timeout: float | None = None) -> Path:
        """Write the newest snapshot to `path` and wait for it (SaveBusy if another save runs)."""
        return self.save_async(path).wait(timeout)

    @property
    def saving(self) -> str:
        job = self._save_job
        return str(job.path) if job is not None and job.running else ""

    def _fresh_snapshot(self):
        """The live map as a snapshot when the map lock is free now (a stopped worker, an idle
        one), else the newest published one: never waits for mapping."""
        if self.lock.acquire(blocking=False):
            try:
                self._publish()
            finally:
                self.lock.release()
        return self.current()

    # ------------------------------------------------------------------------------ loading

    def load(self, path: str | Path):
        """Replace the map by the one in `path` (MapFileError: the current map stays). Returns the
        new live mapper. Frames queued for the old map are mapped into the new one."""
        from rg_core.map.store import load_map

        new = load_map(Path(path).expanduser())   # outside every lock: queries use the old map meanwhile
        self._acquire(0)
        try:
            self.mapper = new
            self.field, self._grounder = getattr(new, "field", None), None
            sset = new.supervision
            self._supervised_count = len(sset.by_keyframe) if sset is not None else 0
            self._train_seconds, self._train_blocked = 0.0, ""
            self._refined_iters = 0
            self._kf_count = len(new.keyframes)
            self.last_error, self.last_result = "", {}
            self._publish(fresh=True)    # nothing of the old map is reused
        finally:
            self.lock.release()
        return new

    # ------------------------------------------------------------------------------ pausing

    def pause(self) -> int:
        """Stop changing the map; frames from now on are counted and dropped. -> frames that were
        queued and are dropped now."""
        self._paused.set()
        n = len(self.queue)
        self.queue.clear()
        return n

    def resume(self) -> None:
        self._paused.clear()
        self.queue.wake()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()
