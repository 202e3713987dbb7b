"""The node's outputs: the publishers (the last answer's cloud and markers and the scene graph
latched, so RViz or `ros2 topic echo` started later still gets them) and what the timers publish:
masks of the last answer in the current camera, the scene graph, the map cloud, diagnostics."""
from __future__ import annotations

import json
import queue
import threading

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, PointCloud2
from visualization_msgs.msg import MarkerArray

from rg_core.grounding.result import GroundingResult

from . import convert as cv
from .params import QOS_OVERRIDES
from .markers import graph_markers, result_markers
from .params import DIAGNOSTICS_TOPIC, NodeParams
from .pointcloud import to_pointcloud2


class NodeOutputs:
    """Mixin of GroundingNode: its publishers and periodic publishing. Uses the node's parameters
    (self.p), worker, latest camera and answer (_camera, _last_result under _state_lock), _warn."""

    def _make_outputs(self, p: NodeParams) -> None:
        """The publishers (the services are the node's)."""
        from rg_interfaces.msg import SceneGraph

        def pub(kind, name, qos):
            return self.create_publisher(kind, name, qos, qos_overriding_options=QOS_OVERRIDES)

        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_amodal = pub(Image, "~/amodal_mask", 1)
        self.pub_visible = pub(Image, "~/visible_mask", 1)
        self.pub_grounded = pub(PointCloud2, "~/grounded_cloud", latched)
        self.pub_markers = pub(MarkerArray, "~/markers", latched)
        self.pub_graph = pub(SceneGraph, "~/scene_graph", latched)
        self.pub_graph_markers = pub(MarkerArray, "~/scene_graph_markers", latched)
        self.pub_map_cloud = pub(PointCloud2, "~/map_cloud", 1)
        self.pub_status = pub(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._answers: queue.SimpleQueue = queue.SimpleQueue()   # answers to publish (_answer_thread)
        threading.Thread(target=self._answer_thread, name="rg-answer-publisher", daemon=True).start()

    def _make_timers(self, p: NodeParams) -> None:
        """Status always; masks, map cloud and scene graph at their rates (0: off)."""
        self.create_timer(max(p.status_period, 0.05), self._on_status, callback_group=MutuallyExclusiveCallbackGroup())
        if p.mask_rate > 0:
            self.create_timer(1.0 / p.mask_rate, self._on_masks, callback_group=MutuallyExclusiveCallbackGroup())
        if p.map_cloud_period > 0:
            self.create_timer(p.map_cloud_period, self._on_map_cloud, callback_group=MutuallyExclusiveCallbackGroup())
        self._graph_lock = threading.Lock()
        self._graph_sent: list | None = None       # the object list last published (the grounder's cached one)
        if p.scene_graph_period > 0:
            self.create_timer(p.scene_graph_period, self._on_scene_graph, callback_group=MutuallyExclusiveCallbackGroup())

    def _publish_reset(self) -> None:
        """After a reset: empty answer markers and scene-graph labels; the next graph is new."""
        self.pub_markers.publish(result_markers(GroundingResult(False, "reset"), self.p.map_frame, self._stamp_now()))
        with self._graph_lock:
            self._graph_sent = None
        self.pub_graph_markers.publish(graph_markers([], np.array([0.0, 0.0, 1.0]), self.p.map_frame, self._stamp_now()))

    def _publish_answer(self, result: GroundingResult, cloud=None, stamp=None, graph: bool = False) -> None:
        """Make `result` (a /ground, clicked-point or teach answer) the current answer now, and publish
        its grounded cloud and markers (latched), its masks on the current camera (then at mask_rate)
        and, with `graph`, the scene graph if it changed, from the answer thread: the service's reply
        does not wait for them (the newest answer wins when they fall behind)."""
        stamp = stamp if stamp is not None else self._stamp_now()
        with self._state_lock:
            self._last_result = result
        self._answers.put((result, cloud, stamp, graph))

    def _publish_graph_later(self, stamp) -> None:
        """The scene graph (if it changed) from the answer thread: an unsuccessful answer built it."""
        self._answers.put((None, None, stamp, True))

    def _answer_thread(self) -> None:
        while True:
            item = self._answers.get()
            if item is None:
                return
            while not self._answers.empty():   # only the newest answer is worth drawing
                nxt = self._answers.get()
                if nxt is None:
                    return
                item = nxt[:3] + (nxt[3] or item[3],) if nxt[0] is not None else item[:3] + (True,)
            result, cloud, stamp, graph = item
            try:
                if result is not None:
                    if cloud is None:
                        cloud = cv.result_to_response(result, self.p.map_frame, stamp).cloud
                    self.pub_grounded.publish(cloud)
                    self.pub_markers.publish(result_markers(result, self.p.map_frame, stamp,
                                                            box_alpha=self.p.marker_alpha))
                    self._on_masks()
                if graph:
                    self._on_scene_graph()
            except Exception as exc:  # noqa: BLE001 - the node lives; a shutdown mid-publish ends here
                self._warn("answer_publish", f"answer not published: {type(exc).__name__}: {exc}")

    def _on_masks(self) -> None:
        with self._state_lock:
            result, cam = self._last_result, self._camera
        if result is None or cam is None or not result.objects:
            return
        K, w, h, c2w, frame_id, stamp, depth, rgb = cam
        try:
            masks = self.worker.masks(result, K, c2w, w, h, depth=depth, image=rgb)
        except Exception as exc:  # noqa: BLE001
            return self._warn("masks", f"mask rendering failed: {type(exc).__name__}: {exc}")
        if masks is None:
            return
        amodal, visible = masks
        self.pub_amodal.publish(cv.mask_to_image(amodal, frame_id, stamp))
        self.pub_visible.publish(cv.mask_to_image(visible, frame_id, stamp))

    def _on_scene_graph(self) -> None:
        """Publish the scene graph (latched) and its text markers when the map's graph changed."""
        with self._graph_lock:
            graph = self.worker.scene_graph(timeout=self.p.ground_timeout)
            if graph is None or graph[0] is self._graph_sent:
                return
            objs, rels, up = graph
            stamp = self._stamp_now()
            try:
                self.pub_graph.publish(cv.graph_to_msg(objs, rels, up, self.p.map_frame, stamp))
                self.pub_graph_markers.publish(graph_markers(objs, up, self.p.map_frame, stamp))
            except Exception as exc:  # noqa: BLE001 - the node lives
                return self._warn("graph", f"scene graph not published: {type(exc).__name__}: {exc}")
            self._graph_sent = objs
            self.get_logger().info(f"scene graph: {len(objs)} objects, {len(rels)} relations")

    def _on_map_cloud(self) -> None:
        if self.pub_map_cloud.get_subscription_count() == 0:
            return
        snap = self.worker.snapshot(self.p.map_cloud_max_points)
        if snap is not None:
            self.pub_map_cloud.publish(to_pointcloud2(snap[0], snap[1], self.p.map_frame, self._stamp_now()))

    def status(self) -> dict:
        """The diagnostics' values: the worker's counters and the inputs'."""
        st = self.worker.stats()
        st["sync_dropped"] = sum(self.sync.dropped.values())
        st["sync_mixed"] = self.sync.mixed   # sets refused: they would have paired messages of two frames
        st["input_errors"] = dict(self.input_errors)
        st["messages"] = dict(self.msgs_in)
        st["pose_source"] = self.p.pose_source
        st["tf_dropped"] = self.tf_dropped
        st["tf_waiting"] = len(self._tf_pending)
        st["clicks"] = dict(getattr(self, "clicks", {}))   # clicked points answered / refused (teaching.py)
        st["taught"] = self.worker.taught_names()
        return st

    def _on_status(self) -> None:
        st = self.status()
        if not self.worker.alive:
            level, msg = DiagnosticStatus.ERROR, f"mapping worker {st['worker']}"
        elif st["perception"].startswith("failed"):
            level, msg = DiagnosticStatus.WARN, f"perception {st['perception']}"
        elif self._last_image_time is not None and self._last_info_time is None:
            level, msg = DiagnosticStatus.WARN, f"no CameraInfo on {self.topics['info']}"
        else:
            level, msg = DiagnosticStatus.OK, (f"{st['keyframes']} keyframes, {st['gaussians']} Gaussians, "
                                               f"queue {st['queue']}/{st['queue_size']}, {st['dropped']} dropped")
        values = [KeyValue(key=k, value=v if isinstance(v, str) else json.dumps(v)) for k, v in st.items()]
        s = DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: mapping", message=msg,
                             hardware_id="rg_ros", values=values)
        self.pub_status.publish(DiagnosticArray(header=cv.header("", self._stamp_now()), status=[s]))
