"""The node's map-server services: `~/save_map` and `~/load_map` (rg_interfaces/srv/MapFile: a
path; an empty one saves to the `save_path` parameter), `~/pause_mapping` and `~/resume_mapping`
(std_srvs/Trigger). The worker does the work (map_admin.py): a save writes a snapshot in its own
thread and a second one while it runs is refused ("already saving ..."), a load swaps the map in
one step, and /ground is answered throughout (its own callback group, reading snapshots).

Each service has its own reentrant callback group: a save waiting for its file never holds up a
pause, a load or a second save's "already saving" answer.
"""
from __future__ import annotations

from pathlib import Path

from rclpy.callback_groups import ReentrantCallbackGroup
from std_srvs.srv import Trigger


class MapServices:
    """Mixin of GroundingNode: uses its parameters (p), worker, logger and _publish_reset."""

    def _make_map_services(self) -> None:
        from rg_interfaces.srv import MapFile

        for name, kind, cb in (("~/save_map", MapFile, self._on_save), ("~/load_map", MapFile, self._on_load),
                               ("~/pause_mapping", Trigger, self._on_pause),
                               ("~/resume_mapping", Trigger, self._on_resume)):
            self.create_service(kind, name, cb, callback_group=ReentrantCallbackGroup())

    def _counts(self) -> str:
        st = self.worker.stats()
        return f"{st['keyframes']} keyframes, {st['gaussians']} Gaussians"

    def _on_save(self, request, response):
        from .map_admin import SaveBusy

        path = Path(request.path.strip() or self.p.save_path).expanduser()
        response.path = str(path.resolve())
        try:
            job = self.worker.save_async(path)
        except SaveBusy as exc:
            response.success, response.message = False, str(exc)
            self.get_logger().warning(response.message)
            return response
        try:
            out = job.wait()
        except Exception as exc:  # noqa: BLE001 - the caller learns why; the map is untouched
            response.success, response.message = False, f"could not save {path}: {type(exc).__name__}: {exc}"
            self.get_logger().error(response.message)
            return response
        response.success = True
        response.message = f"saved {out.resolve()} ({job.keyframes} keyframes, {job.gaussians} Gaussians)"
        self.get_logger().info(response.message)
        return response

    def _on_load(self, request, response):
        from rg_core.map.store import MapFileError

        raw = request.path.strip()
        if not raw:
            response.success, response.message = False, "load_map: empty path (give the map file to load)"
            return response
        path = Path(raw).expanduser()
        response.path = str(path.resolve())
        try:
            self.worker.load(path)
        except (MapFileError, OSError) as exc:
            response.success, response.message = False, f"{exc}; the current map is unchanged"
            self.get_logger().error(response.message)
            return response
        with self._state_lock:
            self._last_result = None
        self._publish_reset()
        response.success, response.message = True, f"loaded {response.path} ({self._counts()})"
        self.get_logger().info(response.message)
        return response

    def _on_pause(self, request, response):
        was = self.worker.paused
        n = self.worker.pause()
        response.success = True
        response.message = ("mapping already paused" if was else "mapping paused") + (
            f" ({n} queued frames dropped)" if n else "") + f": frames are counted and dropped, queries answered; {self._counts()}"
        self.get_logger().info(response.message)
        return response

    def _on_resume(self, request, response):
        was = self.worker.paused
        self.worker.resume()
        response.success = True
        response.message = (f"mapping resumed ({self.worker.paused_dropped} frames dropped while paused so far)"
                            if was else "mapping was not paused")
        self.get_logger().info(response.message)
        return response
