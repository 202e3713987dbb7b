"""The ROS 2 node: subscriptions -> approximate time sync -> MapWorker; /ground, ~/save_map, ~/reset;
masks, clouds, markers and diagnostics out. Thin: message conversion and calls into rg_core only.

Parameters and names: rg_ros/params.py; running it (signals, executor): rg_ros/run.py.
"""
from __future__ import annotations

import dataclasses
import json
import threading
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from rg_core.geometry.tf_buffer import TFBuffer
from rg_core.grounding.result import GroundingResult
from rg_core.io.ros_images import camera_info_K
from rg_core.io.ros_input import resolve_pose
from rg_core.io.sync import ApproximateTimeSync, SyncedSet
from rg_core.perception.query import parse_mode, query_problem

from . import convert as cv
from .markers import graph_markers, result_markers
from .tf_input import TFInput
from .params import DIAGNOSTICS_TOPIC, GROUND_SERVICE, NODE_NAME, NodeParams, check_unknown_params, declare_params
from .pointcloud import to_pointcloud2
from .worker import Frame, MapWorker

# qos_overrides./<topic>.<publisher|subscription>.{history,depth,reliability} parameters for every topic
_QOS_OVERRIDES = QoSOverridingOptions.with_default_policies()


class GroundingNode(TFInput, Node):
    def __init__(self, node_name: str = NODE_NAME, **kwargs):
        """Parameters come from rcl (--ros-args --params-file / -p, or `parameter_overrides`); a bad
        one is a ValueError naming it (rg-node prints it and exits 2). Names are relative (remapping)."""
        super().__init__(node_name, **kwargs)
        self.p = p = declare_params(self)
        if p.torch_threads > 0:
            import torch

            torch.set_num_threads(p.torch_threads)
        self.worker = self._make_worker(p)
        self._state_lock = threading.Lock()
        self._camera: tuple | None = None   # (K, w, h, cam_to_world, frame_id, stamp, depth, rgb) of the latest frame
        self._last_result: GroundingResult | None = None
        self._last_info_time: float | None = None
        self._last_image_time: float | None = None
        self._first_image_time: float | None = None
        self._warned: dict[str, float] = {}
        self.input_errors: dict[str, int] = {}
        self._make_inputs(p)
        self._make_outputs(p)
        check_unknown_params(self, qos_only=True)   # qos_overrides.* exist once the entities do
        self.create_timer(max(p.status_period, 0.05), self._on_status, callback_group=MutuallyExclusiveCallbackGroup())
        if p.mask_rate > 0:
            self.create_timer(1.0 / p.mask_rate, self._on_masks, callback_group=MutuallyExclusiveCallbackGroup())
        if p.map_cloud_period > 0:
            self.create_timer(p.map_cloud_period, self._on_map_cloud, callback_group=MutuallyExclusiveCallbackGroup())
        self._graph_lock = threading.Lock()
        self._graph_sent: list | None = None       # the object list last published (the grounder's cached one)
        if p.scene_graph_period > 0:
            self.create_timer(p.scene_graph_period, self._on_scene_graph, callback_group=MutuallyExclusiveCallbackGroup())
        self.worker.start()
        pose_from = {"tf": f"TF {p.map_frame} <- image frame", "topic": f"PoseStamped {self.topics.get('pose')}",
                     "odometry": f"Odometry {self.topics.get('pose')}"}[p.pose_source]
        self.get_logger().info(
            f"listening: colour {self.topics['color']}, depth {self.topics['depth']}, info {self.topics['info']}, "
            f"pose from {pose_from}; service {self.resolve_service_name(GROUND_SERVICE)}; "
            f"features {'on' if p.features else 'off'}")

    def _make_worker(self, p: NodeParams) -> MapWorker:
        """The library side: rg config with the node's overrides, the start-up map, the models."""
        from rg_core.config import load_config

        log = self.get_logger()
        cfg = load_config(p.rg_config or None)
        over_map = {k: v for k, v in (("width", p.map_width), ("iters_per_keyframe", p.iters_per_keyframe),
                                      ("max_gaussians", p.max_gaussians), ("max_keyframes", p.max_keyframes))
                  if v > 0}
        cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, **over_map),
                                  ground=dataclasses.replace(cfg.ground, min_confidence=p.min_confidence))
        if p.preset:
            cfg.models.preset = p.preset     # its confidence model calibrates the answers
        else:
            from rg_core.models import perception_spec

            offline = perception_spec("offline")
            if (p.mask_generator, p.embedder) != (offline[0], offline[2]):
                cfg.models.preset = ""       # models of no preset: no calibrated confidence, no abstention
        mapper = None
        if p.load_map:
            from rg_core.map.store import load_map

            mapper = load_map(p.load_map)   # MapFileError: the node does not start (rg-node says why)
            log.info(f"loaded map {p.load_map}: {mapper.stats()['keyframes']} keyframes, "
                     f"{len(mapper.gaussians)} Gaussians")
        wcfg = p.worker_config()
        loader = None
        if p.preset:
            from rg_core.models import ModelError, apply_reasoner, make_perception

            try:
                apply_reasoner(p.preset, cfg)
            except ModelError as exc:  # the node runs; implicit queries use the text reasoner
                log.error(f"{exc}; implicit queries use the text reasoner")
            wcfg.mask_generator = wcfg.embedder = f"preset {p.preset}"
            loader = lambda: make_perception(p.preset, cfg.models)  # noqa: E731 - errors name the fetch command
        return MapWorker(cfg, wcfg, mapper, logger=_RosLogAdapter(log), perception_loader=loader)

    def _make_inputs(self, p: NodeParams) -> None:
        """Subscriptions (relative names resolved through the remappings; a compressed transport
        subscribes to <base>/<transport> as image_transport does), the synchroniser and TF."""
        self.inputs = p.input_config()
        self.tf = TFBuffer(p.tf_cache_time, p.tf_extrapolation, p.tf_max_gap)
        self._tf_pending: list[tuple[float, Frame, object]] = []   # (deadline, frame without pose, pose message)
        self._tf_lock = threading.Lock()   # the pending frames: touched by the sensor and the TF callbacks
        self.tf_dropped = 0
        roles = ("color", "depth", "info") + (("pose",) if p.pose_source != "tf" else ())
        self.sync = ApproximateTimeSync(roles, p.sync_queue_size, p.sync_slop, callback=self._on_synced)
        self.msgs_in = dict.fromkeys(roles, 0)   # messages taken per input (diagnostics 'messages')
        self.topics = {"color": self._transport_topic("rgb/image", p.color_transport),
                       "depth": self._transport_topic("depth/image", p.depth_transport),
                       "info": self.resolve_topic_name("rgb/camera_info")}
        types = {"color": Image if p.color_transport == "raw" else CompressedImage,
                 "depth": Image if p.depth_transport == "raw" else CompressedImage, "info": CameraInfo}
        if p.pose_source == "topic":
            self.topics["pose"], types["pose"] = self.resolve_topic_name("pose"), PoseStamped
        elif p.pose_source == "odometry":
            from nav_msgs.msg import Odometry

            self.topics["pose"], types["pose"] = self.resolve_topic_name("odom"), Odometry
        sensors = MutuallyExclusiveCallbackGroup()
        for role, topic in self.topics.items():
            self.create_subscription(types[role], topic, lambda m, r=role: self._on_msg(r, m), qos_profile_sensor_data,
                                     callback_group=sensors, qos_overriding_options=_QOS_OVERRIDES)
        # TF in its own group: processed alongside the images, never queued behind them (at one message
        # per topic and executor turn, /tf fell behind the images on a loaded CPU and frames timed out)
        self._subscribe_tf(MutuallyExclusiveCallbackGroup())

    def _make_outputs(self, p: NodeParams) -> None:
        """Services and publishers; the last answer (cloud, markers) is latched, so RViz or `ros2
        topic echo` started later still gets it."""
        from rg_interfaces.msg import SceneGraph
        from rg_interfaces.srv import Ground

        self.create_service(Ground, GROUND_SERVICE, self._on_ground, callback_group=MutuallyExclusiveCallbackGroup())
        admin = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, "~/save_map", self._on_save, callback_group=admin)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=admin)

        def pub(kind, name, qos):
            return self.create_publisher(kind, name, qos, qos_overriding_options=_QOS_OVERRIDES)

        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_amodal = pub(Image, "~/amodal_mask", 1)
        self.pub_visible = pub(Image, "~/visible_mask", 1)
        self.pub_grounded = pub(PointCloud2, "~/grounded_cloud", latched)
        self.pub_markers = pub(MarkerArray, "~/markers", latched)
        self.pub_graph = pub(SceneGraph, "~/scene_graph", latched)
        self.pub_graph_markers = pub(MarkerArray, "~/scene_graph_markers", latched)
        self.pub_map_cloud = pub(PointCloud2, "~/map_cloud", 1)
        self.pub_status = pub(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)

    # ------------------------------------------------------------------------------ names

    def _transport_topic(self, base: str, transport: str) -> str:
        name = self.resolve_topic_name(base)
        return name if transport == "raw" else f"{name}/{transport}"

    # ------------------------------------------------------------------------------ helpers

    def _warn(self, key: str, msg: str, period: float = 5.0) -> None:
        """Count and log an input problem: the first of each kind at once, then at most every `period` s."""
        n = self.input_errors[key] = self.input_errors.get(key, 0) + 1
        now = time.monotonic()
        if n == 1 or now - self._warned.get(key, 0.0) >= period:
            self._warned[key] = now
            self.get_logger().warning(f"{msg}" + (f" ({n} so far)" if n > 1 else ""))

    def _stamp_now(self):
        return self.get_clock().now().to_msg()

    # ------------------------------------------------------------------------------ input

    def _on_msg(self, topic: str, msg) -> None:
        now = time.monotonic()
        self.msgs_in[topic] += 1
        if topic == "info":
            self._last_info_time = now
        elif topic == "color":
            if self._first_image_time is None:
                self._first_image_time = now
            self._last_image_time = now
            since = now - (self._last_info_time if self._last_info_time is not None else self._first_image_time)
            if since > self.p.camera_info_timeout:
                self._warn("camera_info", f"no CameraInfo on {self.topics['info']} for {since:.1f} s: "
                           "frames cannot be mapped without intrinsics")
        try:
            self.sync.add(topic, cv.from_time(msg.header.stamp), msg)
        except Exception as exc:  # noqa: BLE001 - a bad message never kills the callback thread
            self._warn(f"{topic}_msg", f"{topic} message dropped: {type(exc).__name__}: {exc}")

    def _on_synced(self, s: SyncedSet) -> None:
        color, depth, info = s.msgs[:3]
        pose = s.msgs[3] if len(s.msgs) > 3 else None
        p = self.p
        try:
            rgb = cv.image_to_rgb(color)
        except ValueError as exc:
            return self._warn("color", f"colour image rejected ({self.topics['color']}): {exc}")
        try:
            d = cv.image_to_depth(depth)
        except ValueError as exc:
            return self._warn("depth", f"depth image rejected ({self.topics['depth']}): {exc}")
        if d.shape != rgb.shape[:2]:
            return self._warn("size", f"frame rejected: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                              f"{d.shape[1]}x{d.shape[0]} (depth must be registered to the colour image)")
        try:
            K, (w, h) = camera_info_K(info)
        except ValueError as exc:
            return self._warn("camera_info_bad", f"frame rejected: {exc}")
        if (w, h) != (rgb.shape[1], rgb.shape[0]):
            return self._warn("size_info", f"frame rejected: CameraInfo is {w}x{h} but the colour image is "
                              f"{rgb.shape[1]}x{rgb.shape[0]}")
        if p.pose_source == "topic":
            try:
                c2w = resolve_pose(self.tf, self.inputs, color.header.frame_id, s.stamps[0], pose)
            except ValueError as exc:   # PoseError (NaN, inf, non-unit quaternion) or the wrong frame
                return self._warn("pose", f"frame rejected: bad pose on {self.topics['pose']}: {exc}")
            return self._submit(Frame(rgb, d, K, c2w, s.stamps[0], color.header.frame_id), color.header.stamp, w, h)
        frame = Frame(rgb, d, K, np.eye(4), s.stamps[0], color.header.frame_id)
        with self._tf_lock:
            self._tf_pending.append((time.monotonic() + p.tf_wait, frame, (pose, color.header.stamp, w, h)))
            if len(self._tf_pending) > max(2 * p.frame_queue_size, 4):   # bounded: the oldest waits no longer
                _, old, extra = self._tf_pending.pop(0)
                self._tf_drop(old, extra[0], "too many frames waiting for their transform")
        self._try_pending()

    def _submit(self, frame: Frame, stamp_msg, w: int, h: int) -> None:
        with self._state_lock:
            self._camera = (frame.K, w, h, frame.cam_to_world, frame.frame_id, stamp_msg, frame.depth, frame.rgb)
        if self.worker.submit(frame):
            self._warn("queue_drop", f"mapping is slower than the input: dropped the oldest queued frame "
                       f"(queue of {self.worker.queue.maxsize}, {self.worker.queue.dropped} dropped)", period=10.0)

    # ------------------------------------------------------------------------------ services

    def _on_ground(self, request, response):
        p = self.p
        query = request.query
        t = time.perf_counter()
        problem = query_problem(query, p.max_query_chars)   # the node's own limit (a parameter)
        try:
            mode = parse_mode(request.mode)
        except ValueError as exc:
            problem = problem or str(exc)
        if problem:
            result = GroundingResult(False, problem, query=query[:200])
        else:
            with self._state_lock:   # view-dependent words ("left of", "nearest to me"): the robot's camera
                cam = self._camera[3] if self._camera is not None else None
            result = self.worker.ground(query, mode, int(request.max_results) or p.max_results, p.ground_timeout,
                                        cam_to_world=cam)
        stamp = self._stamp_now()
        try:
            response = cv.result_to_response(result, p.map_frame, stamp, response=response)
        except Exception as exc:  # noqa: BLE001 - a broken result must still get an answer
            self.get_logger().error(f"ground: cannot convert the result: {exc}")
            response.success, response.message = False, f"internal error converting the result: {exc}"
            return response
        log = self.get_logger()
        short = query[:60] + ("..." if len(query) > 60 else "")
        if result.success:
            log.info(f"ground '{short}': {result.message} ({time.perf_counter() - t:.2f} s)")
            with self._state_lock:
                self._last_result = result
            self.pub_grounded.publish(response.cloud)
            self.pub_markers.publish(result_markers(result, p.map_frame, stamp, box_alpha=p.marker_alpha))
            self._on_masks()
        else:
            log.warning(f"ground '{short}' failed: {result.message}")
        if "graph" in result.timings:   # the answer built or used the scene graph: publish it if new
            self._on_scene_graph()
        return response

    def _on_save(self, request, response):
        path = Path(self.p.save_path).expanduser()
        try:
            out = self.worker.save(path)
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, f"could not save {path}: {type(exc).__name__}: {exc}"
            self.get_logger().error(response.message)
            return response
        st = self.worker.stats()
        response.success = True
        response.message = f"saved {out.resolve()} ({st['keyframes']} keyframes, {st['gaussians']} Gaussians)"
        self.get_logger().info(response.message)
        return response

    def _on_reset(self, request, response):
        self.worker.reset()
        self.sync.reset()
        self.tf.clear()
        with self._tf_lock:
            self._tf_pending = []
        with self._state_lock:
            self._last_result = None
        self.pub_markers.publish(result_markers(GroundingResult(False, "reset"), self.p.map_frame, self._stamp_now()))
        with self._graph_lock:
            self._graph_sent = None
        self.pub_graph_markers.publish(graph_markers([], np.array([0.0, 0.0, 1.0]), self.p.map_frame, self._stamp_now()))
        response.success, response.message = True, "map reset: 0 keyframes, 0 Gaussians"
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------------------ output

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
        st = self.worker.stats()
        st["sync_dropped"] = sum(self.sync.dropped.values())
        st["sync_mixed"] = self.sync.mixed   # sets refused: they would have paired messages of two frames
        st["input_errors"] = dict(self.input_errors)
        st["messages"] = dict(self.msgs_in)
        st["pose_source"] = self.p.pose_source
        st["tf_dropped"] = self.tf_dropped
        st["tf_waiting"] = len(self._tf_pending)
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

    # ------------------------------------------------------------------------------ shutdown

    def shutdown(self, timeout: float = 30.0) -> None:
        """Stop the worker after its current step; save the map if save_on_shutdown."""
        log = self.get_logger()
        if not self.worker.stop(timeout):
            log.warning(f"mapping worker did not stop within {timeout:.0f} s")
        if self.p.save_on_shutdown:
            try:
                out = self.worker.save(Path(self.p.save_path).expanduser())
                log.info(f"map saved on shutdown: {out}")
            except Exception as exc:  # noqa: BLE001
                log.error(f"could not save the map on shutdown: {exc}")


class _RosLogAdapter:
    """logging.Logger-like front of an rclpy logger for the worker (printf-style arguments)."""

    def __init__(self, logger):
        self._l = logger

    def _fmt(self, msg, args):
        return str(msg) % args if args else str(msg)

    def debug(self, msg, *args):
        self._l.debug(self._fmt(msg, args))

    def info(self, msg, *args):
        self._l.info(self._fmt(msg, args))

    def warning(self, msg, *args):
        self._l.warning(self._fmt(msg, args))

    def error(self, msg, *args):
        self._l.error(self._fmt(msg, args))


