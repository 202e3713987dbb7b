"""The node's teaching side: RViz's "Publish Point" tool on `clicked_point` (the object there
becomes the current answer), `~/teach` (name the object at a point, or the current answer) and
`~/forget`. Points arrive in any TF frame and are transformed into `map_frame` with the node's TF
buffer; the worker does the rest under its map lock (worker_teach.py, rg_core/grounding/point.py
and teach.py). A refusal (a bad name, NaN, a frame with no transform, nothing mapped near the
point, a map not ready) is answered (services) or logged (clicks) and changes nothing.
"""
from __future__ import annotations

import threading

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import QoSProfile, ReliabilityPolicy

from rg_core.geometry.tf_buffer import ExtrapolationError, TFError
from rg_core.grounding.point import check_point
from rg_core.grounding.result import GroundingResult
from rg_core.map.taught import check_name

from . import convert as cv
from .params import CLICKED_POINT_TOPIC, QOS_OVERRIDES, NodeParams


class FrameProblem(ValueError):
    """A point without a frame, or in a frame with no known transform to map_frame."""


def _xyz(p) -> str:
    return "({:.3f}, {:.3f}, {:.3f})".format(*np.asarray(p, np.float64))


class Teaching:
    """Mixin of GroundingNode: the clicked_point input and the ~/teach and ~/forget services. Uses
    the node's parameters (self.p), worker, TF buffer (self.tf), _warn and NodeOutputs'
    _publish_answer / _on_scene_graph."""

    def _make_teaching(self, p: NodeParams) -> None:
        from rg_interfaces.srv import Forget, Teach

        self.clicks = {"answered": 0, "refused": 0}   # clicked points (diagnostics 'clicks')
        group = MutuallyExclusiveCallbackGroup()   # teaching and forgetting: one at a time, beside /ground
        self.create_service(Teach, "~/teach", self._on_teach, callback_group=group)
        self.create_service(Forget, "~/forget", self._on_forget, callback_group=group)
        # RViz's Publish Point tool: reliable, depth 10 (rviz_default_plugins' PointTool)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.topics["clicked_point"] = self.resolve_topic_name(CLICKED_POINT_TOPIC)
        self.create_subscription(PointStamped, CLICKED_POINT_TOPIC, self._on_clicked, qos,
                                 callback_group=MutuallyExclusiveCallbackGroup(), qos_overriding_options=QOS_OVERRIDES)

    # ------------------------------------------------------------------------------ points

    def _to_map(self, msg: PointStamped) -> np.ndarray:
        """A PointStamped as [3] in map_frame; ValueError saying what is wrong (NaN/inf, no frame,
        no transform from its frame)."""
        raw = check_point([msg.point.x, msg.point.y, msg.point.z])
        frame = msg.header.frame_id.strip().lstrip("/")
        target = self.p.map_frame
        if not frame:
            raise FrameProblem(f"the point has no frame_id: give its TF frame (e.g. '{target}')")
        if frame == target:
            return raw
        stamp = cv.from_time(msg.header.stamp)
        try:
            try:
                T = self.tf.lookup(target, frame, stamp)
            except ExtrapolationError:   # a click stamped after the newest transform: the latest will do
                if stamp == 0:
                    raise
                T = self.tf.lookup(target, frame, 0)
        except TFError as exc:
            raise FrameProblem(f"no transform is known from the point's frame '{frame}' to the map frame "
                             f"'{target}': {exc}") from None
        return check_point(T[:3, :3] @ raw + T[:3, 3])

    # ------------------------------------------------------------------------------ clicked_point

    def _on_clicked(self, msg: PointStamped) -> None:
        where = f"({msg.point.x:g}, {msg.point.y:g}, {msg.point.z:g}) in '{msg.header.frame_id}'"
        try:
            point = self._to_map(msg)
        except ValueError as exc:
            self.clicks["refused"] += 1
            key = "clicked_point_frame" if isinstance(exc, FrameProblem) else "clicked_point_bad"
            return self._warn(key, f"clicked point {where} ignored: {exc}; nothing changed")
        res = self.worker.point_answer(point, self.p.ground_timeout)
        if not res.success:
            self.clicks["refused"] += 1
            return self._warn("clicked_point", f"clicked point {where} ignored: {res.message}; nothing changed")
        self.clicks["answered"] += 1
        names = ", ".join(f"{n!r} ({s:.2f})" for n, s in res.names[:3]) or "nothing it can name"
        n = len(res.objects[0].gaussian_ids)
        self.get_logger().info(f"clicked {_xyz(point)}: {n} Gaussians, the map thinks it is {names}; "
                               f"confidence {res.confidence:.2f}. It is the current answer: ~/teach with "
                               "use_current_answer names it")
        self._publish_answer(res)

    # ------------------------------------------------------------------------------ services

    def _on_teach(self, request, response):
        log = self.get_logger()
        response.taught = self.worker.taught_names()
        try:
            check_name(request.name)
            if request.use_current_answer:
                with self._state_lock:
                    current = self._last_result
                if current is None or not current.objects:
                    raise ValueError("there is no current answer to name: call /ground, or click a point in RViz "
                                     f"({self.topics['clicked_point']}), first, or give a point")
                result, name, taught = self.worker.teach(request.name, result=current, timeout=self.p.ground_timeout)
            else:
                point = self._to_map(request.point)
                result, name, taught = self.worker.teach(request.name, point=point, timeout=self.p.ground_timeout)
        except ValueError as exc:
            result, name, taught = GroundingResult(False, str(exc)), "", response.taught
        try:
            cv.answer_fields(result, self.p.map_frame, self._stamp_now(), response)
        except Exception as exc:  # noqa: BLE001 - a broken result must still get an answer
            log.error(f"teach: cannot convert the result: {exc}")
            response.success, response.message = False, f"internal error converting the result: {exc}"
        response.name, response.taught = name, list(taught)
        short = request.name[:64] + ("..." if len(request.name) > 64 else "")
        if not response.success:
            log.warning(f"teach {short!r} refused: {result.message}; the map is unchanged")
            return response
        log.info(f"taught {name!r}: {result.message}; taught now: {', '.join(map(repr, taught))}")
        self._publish_answer(result, response.cloud)
        self._republish_graph()
        return response

    def _on_forget(self, request, response):
        ok, msg, n, taught = self.worker.forget(request.name, self.p.ground_timeout)
        response.success, response.message, response.forgotten, response.taught = ok, msg, n, list(taught)
        if ok:
            self.get_logger().info(msg)
            self._republish_graph()
        else:
            self.get_logger().warning(f"forget {request.name[:64]!r} refused: {msg}")
        return response

    def _republish_graph(self) -> None:
        """The scene graph (it holds the taught names) once the map is free: in a thread of its own,
        so that the service answers without waiting for the graph to be rebuilt."""
        threading.Thread(target=self._on_scene_graph, name="rg-scene-graph", daemon=True).start()
