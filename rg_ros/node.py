"""The ROS 2 node: subscriptions -> approximate time sync -> MapWorker; /ground, ~/save_map, ~/reset;
masks, clouds, markers and diagnostics out. Thin: message conversion and calls into rg_core only.

Every parameter is declared from `NodeParams` (the one place; config/grounding.yaml lists them all).
"""
from __future__ import annotations

import dataclasses
import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from rg_core.geometry.tf_buffer import TFBuffer, TFError
from rg_core.grounding.result import GroundingResult

from . import convert as cv
from .markers import result_markers
from .pointcloud import to_pointcloud2
from .sync import ApproximateTimeSync, SyncedSet
from .worker import Frame, MapWorker, WorkerConfig

NODE_NAME = "rg_node"


@dataclass
class NodeParams:
    """The node's ROS parameters (name, default; the type follows the default)."""

    color_topic: str = "/camera/color/image_raw"
    """sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8); a name ending /compressed subscribes to
    sensor_msgs/CompressedImage (jpeg/png), as image_transport names it."""
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    """sensor_msgs/Image, 16UC1 (mm) or 32FC1 (m), registered to the colour image; a name ending
    /compressedDepth subscribes to image_transport's compressedDepth CompressedImage."""
    camera_info_topic: str = "/camera/color/camera_info"
    """sensor_msgs/CameraInfo of the colour camera."""
    pose_source: str = "tf"
    """tf: look up map_frame <- the colour image's header.frame_id on /tf + /tf_static at its stamp;
    topic: geometry_msgs/PoseStamped on pose_topic; odometry: nav_msgs/Odometry on odom_topic
    (chained with TF to the image's frame, and to map_frame when the odometry's frame differs)."""
    pose_topic: str = "/camera/pose"
    """geometry_msgs/PoseStamped of the colour optical frame in map_frame (pose_source topic)."""
    odom_topic: str = "/odom"
    """nav_msgs/Odometry (pose_source odometry)."""
    map_frame: str = "map"
    """Frame of poses, clouds and markers."""
    tf_wait: float = 0.5
    """Seconds a frame waits for its transform; then it is dropped and counted (diagnostics 'tf')."""
    tf_cache_time: float = 10.0
    """Seconds of dynamic TF history kept."""
    tf_max_gap: float = 0.5
    """A dynamic TF link is not interpolated across a longer gap between samples (s); 0 = any gap (tf2)."""
    tf_extrapolation: float = 0.0
    """Seconds past a link's newest (or before its oldest) sample where its nearest sample is used (tf2: 0)."""
    ground_service: str = "/ground"
    """Name of the rg_interfaces/Ground service."""
    sync_queue_size: int = 10
    """Messages per topic kept by the approximate time synchroniser."""
    sync_slop: float = 0.05
    """Largest stamp spread (s) of one synchronised set."""
    frame_queue_size: int = 4
    """Frames waiting for the mapper; the oldest is dropped (and counted) when full."""
    rg_config: str = ""
    """rg YAML configuration (map and field sections); empty = defaults."""
    map_width: int = 0
    """Mapper working width override (0 = rg_config's map.width)."""
    iters_per_keyframe: int = 0
    """Optimisation iterations per keyframe override (0 = rg_config's)."""
    max_gaussians: int = 0
    """Memory bound override (0 = rg_config's)."""
    load_map: str = ""
    """Map file loaded at start-up (empty = start with an empty map)."""
    save_path: str = "rg_map.pt"
    """Where ~/save_map (and a save on shutdown) writes the map."""
    save_on_shutdown: bool = False
    """Save the map to save_path when the node shuts down (SIGINT)."""
    features: bool = True
    """Keyframe supervision and feature-field training when the mapper is idle."""
    mask_generator: str = "rgbd"
    """Mask generator backend of the supervision."""
    embedder: str = "conse"
    """Image-text embedder backend of the supervision."""
    preset: str = ""
    """Named models (rg_core/models): offline, paper, paper_cpu; overrides mask_generator, embedder and the
    reasoner ("" = those parameters). Missing models are logged with the `rg models ...` command to run."""
    train_slice: float = 0.5
    """Seconds of field training per idle slice."""
    train_seconds_max: float = 30.0
    """Field training seconds after each supervision change (0 = whenever idle)."""
    refine_iters: int = 0
    """Map refinement iterations per idle slice (0 = off)."""
    torch_threads: int = 0
    """torch intra-op threads (0 = torch's default)."""
    max_results: int = 1
    """Objects returned when a request says max_results = 0."""
    max_query_chars: int = 1000
    """Longer queries are refused."""
    ground_timeout: float = 30.0
    """Seconds a grounding call waits for the map lock."""
    mask_rate: float = 2.0
    """Hz of ~/amodal_mask and ~/visible_mask for the last grounded targets (0 = off)."""
    map_cloud_period: float = 5.0
    """Seconds between ~/map_cloud messages (0 = off); only sent while someone subscribes."""
    map_cloud_max_points: int = 50000
    """Gaussians per ~/map_cloud message (evenly subsampled)."""
    status_period: float = 1.0
    """Seconds between diagnostics messages."""
    diagnostics_topic: str = "/diagnostics"
    """diagnostic_msgs/DiagnosticArray status topic."""
    camera_info_timeout: float = 5.0
    """Warn when images arrive but no CameraInfo came for this long (s)."""
    marker_alpha: float = 0.25
    """Opacity of the grounded boxes (CUBE markers)."""


PARAM_NAMES = tuple(f.name for f in dataclasses.fields(NodeParams))
POSE_SOURCES = ("tf", "topic", "odometry")


def _final(exc: TFError) -> bool:
    """A lookup error that waiting cannot cure: data already past the stamp (a gap, the past) or a loop."""
    from rg_core.geometry.tf_buffer import LoopError

    msg = str(exc)
    return isinstance(exc, LoopError) or "falls in a gap" in msg or "extrapolation into the past" in msg


def coerce_params(values: dict, where: str = "parameters") -> dict:
    """Check names and types against NodeParams (ints accepted for floats); raise ValueError naming the key."""
    defaults = NodeParams()
    out = {}
    for k, v in values.items():
        if k not in PARAM_NAMES:
            raise ValueError(f"{where}: unknown parameter '{k}' (known: {', '.join(PARAM_NAMES)})")
        d = getattr(defaults, k)
        if isinstance(d, bool):
            ok = isinstance(v, bool)
        elif isinstance(d, int):
            ok = isinstance(v, int) and not isinstance(v, bool)
        elif isinstance(d, float):
            ok = isinstance(v, (int, float)) and not isinstance(v, bool)
            v = float(v) if ok else v
        else:
            ok = isinstance(v, str)
        if not ok:
            raise ValueError(f"{where}: parameter '{k}' must be {type(d).__name__}, got {v!r}")
        out[k] = v
    return out


def read_params_file(path: str | Path, node_name: str = NODE_NAME) -> dict:
    """A ros__parameters YAML -> {name: value} for `node_name` (sections '/**', 'name' and '/name',
    merged in that order). Unknown names and wrong types are errors."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: parameter file not found")
    data = yaml.safe_load(path.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of node names")
    merged: dict = {}
    found = False
    for key in ("/**", node_name.lstrip("/"), "/" + node_name.lstrip("/")):
        sec = data.get(key)
        if sec is None:
            continue
        if not isinstance(sec, dict) or not isinstance(sec.get("ros__parameters", {}), dict):
            raise ValueError(f"{path}: section '{key}' must hold a 'ros__parameters' mapping")
        found = True
        merged.update(_flatten(sec.get("ros__parameters") or {}))
    if not found:
        raise ValueError(f"{path}: no section for node '{node_name}' (sections: {', '.join(map(str, data))})")
    return coerce_params(merged, str(path))


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, name + "."))
        else:
            out[name] = v
    return out


class GroundingNode(Node):
    def __init__(self, node_name: str = NODE_NAME, overrides: dict | None = None, **kwargs):
        over = [Parameter(k, value=v) for k, v in coerce_params(overrides or {}).items()]
        super().__init__(node_name, parameter_overrides=over, **kwargs)
        # -------------------------------------------------------------- parameters (one place)
        for f in dataclasses.fields(NodeParams):
            self.declare_parameter(f.name, getattr(NodeParams(), f.name))
        self.p = NodeParams(**{n: self.get_parameter(n).value for n in PARAM_NAMES})
        p = self.p
        log = self.get_logger()
        if p.torch_threads > 0:
            import torch

            torch.set_num_threads(p.torch_threads)

        # -------------------------------------------------------------- the library
        from rg_core.config import load_config

        cfg = load_config(p.rg_config or None)
        over_map = {k: v for k, v in (("width", p.map_width), ("iters_per_keyframe", p.iters_per_keyframe),
                                      ("max_gaussians", p.max_gaussians)) if v > 0}
        cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, **over_map))
        mapper = None
        if p.load_map:
            from rg_core.map.store import load_map

            mapper = load_map(p.load_map)   # MapFileError: the node does not start (rg-node says why)
            log.info(f"loaded map {p.load_map}: {mapper.stats()['keyframes']} keyframes, "
                     f"{len(mapper.gaussians)} Gaussians")
        wcfg = WorkerConfig(queue_size=p.frame_queue_size, features=p.features, mask_generator=p.mask_generator,
                            embedder=p.embedder, train_slice=p.train_slice, train_seconds_max=p.train_seconds_max,
                            refine_iters=p.refine_iters)
        loader = None
        if p.preset:
            from rg_core.models import ModelError, apply_reasoner, make_perception

            try:
                apply_reasoner(p.preset, cfg)
            except ModelError as exc:  # the node runs; implicit queries use the text reasoner
                log.error(f"{exc}; implicit queries use the text reasoner")
            wcfg.mask_generator = wcfg.embedder = f"preset {p.preset}"
            loader = lambda: make_perception(p.preset, cfg.models)  # noqa: E731 - errors name the fetch command
        self.worker = MapWorker(cfg, wcfg, mapper, logger=_RosLogAdapter(log), perception_loader=loader)

        # -------------------------------------------------------------- state
        self._state_lock = threading.Lock()
        self._camera: tuple | None = None   # (K, width, height, cam_to_world, frame_id, stamp) of the latest frame
        self._last_result: GroundingResult | None = None
        self._last_info_time: float | None = None
        self._last_image_time: float | None = None
        self._first_image_time: float | None = None
        self._warned: dict[str, float] = {}
        self.input_errors: dict[str, int] = {}

        # -------------------------------------------------------------- interfaces
        if p.pose_source not in POSE_SOURCES:
            raise ValueError(f"parameter pose_source: '{p.pose_source}' is not one of {', '.join(POSE_SOURCES)}")
        self.tf = TFBuffer(p.tf_cache_time, p.tf_extrapolation, p.tf_max_gap)
        self._tf_pending: list[tuple[float, Frame, object]] = []   # (deadline, frame without pose, pose message)
        self._tf_lock = threading.Lock()   # the pending frames: touched by the sensor and the TF callbacks
        self.tf_dropped = 0
        roles = ("color", "depth", "info") + (("pose",) if p.pose_source != "tf" else ())
        self.sync = ApproximateTimeSync(roles, p.sync_queue_size, p.sync_slop, callback=self._on_synced)
        sensors = MutuallyExclusiveCallbackGroup()
        qos = qos_profile_sensor_data
        color_type = CompressedImage if p.color_topic.rstrip("/").endswith("/compressed") else Image
        depth_type = CompressedImage if p.depth_topic.rstrip("/").endswith("/compressedDepth") else Image
        self.create_subscription(color_type, p.color_topic, lambda m: self._on_msg("color", m), qos,
                                 callback_group=sensors)
        self.create_subscription(depth_type, p.depth_topic, lambda m: self._on_msg("depth", m), qos,
                                 callback_group=sensors)
        self.create_subscription(CameraInfo, p.camera_info_topic, lambda m: self._on_msg("info", m), qos,
                                 callback_group=sensors)
        if p.pose_source == "topic":
            self.create_subscription(PoseStamped, p.pose_topic, lambda m: self._on_msg("pose", m), qos,
                                     callback_group=sensors)
        elif p.pose_source == "odometry":
            from nav_msgs.msg import Odometry

            self.create_subscription(Odometry, p.odom_topic, lambda m: self._on_msg("pose", m), qos,
                                     callback_group=sensors)
        # TF in its own group: processed alongside the images, never queued behind them (at one message
        # per topic and executor turn, /tf fell behind the images on a loaded CPU and frames timed out)
        self._subscribe_tf(MutuallyExclusiveCallbackGroup())

        from rg_interfaces.srv import Ground

        self.create_service(Ground, p.ground_service, self._on_ground, callback_group=MutuallyExclusiveCallbackGroup())
        admin = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, "~/save_map", self._on_save, callback_group=admin)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=admin)

        self.pub_amodal = self.create_publisher(Image, "~/amodal_mask", 1)
        self.pub_visible = self.create_publisher(Image, "~/visible_mask", 1)
        self.pub_grounded = self.create_publisher(PointCloud2, "~/grounded_cloud", 1)
        self.pub_markers = self.create_publisher(MarkerArray, "~/markers", 1)
        self.pub_map_cloud = self.create_publisher(PointCloud2, "~/map_cloud", 1)
        self.pub_status = self.create_publisher(DiagnosticArray, p.diagnostics_topic, 10)

        self.create_timer(max(p.status_period, 0.05), self._on_status, callback_group=MutuallyExclusiveCallbackGroup())
        if p.mask_rate > 0:
            self.create_timer(1.0 / p.mask_rate, self._on_masks, callback_group=MutuallyExclusiveCallbackGroup())
        if p.map_cloud_period > 0:
            self.create_timer(p.map_cloud_period, self._on_map_cloud, callback_group=MutuallyExclusiveCallbackGroup())
        self.worker.start()
        pose_from = {"tf": f"TF {p.map_frame} <- image frame", "topic": f"PoseStamped {p.pose_topic}",
                     "odometry": f"Odometry {p.odom_topic}"}[p.pose_source]
        log.info(f"listening: colour {p.color_topic}, depth {p.depth_topic}, info {p.camera_info_topic}, "
                 f"pose from {pose_from}; service {p.ground_service}; features {'on' if p.features else 'off'}")

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
        if topic == "info":
            self._last_info_time = now
        elif topic == "color":
            if self._first_image_time is None:
                self._first_image_time = now
            self._last_image_time = now
            since = now - (self._last_info_time if self._last_info_time is not None else self._first_image_time)
            if since > self.p.camera_info_timeout:
                self._warn("camera_info", f"no CameraInfo on {self.p.camera_info_topic} for {since:.1f} s: "
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
            return self._warn("color", f"colour image rejected ({p.color_topic}): {exc}")
        try:
            d = cv.image_to_depth(depth)
        except ValueError as exc:
            return self._warn("depth", f"depth image rejected ({p.depth_topic}): {exc}")
        if d.shape != rgb.shape[:2]:
            return self._warn("size", f"frame rejected: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                              f"{d.shape[1]}x{d.shape[0]} (depth must be registered to the colour image)")
        try:
            K, (w, h) = cv.camera_info_to_K(info)
        except ValueError as exc:
            return self._warn("camera_info_bad", f"frame rejected: {exc}")
        if (w, h) != (rgb.shape[1], rgb.shape[0]):
            return self._warn("size_info", f"frame rejected: CameraInfo is {w}x{h} but the colour image is "
                              f"{rgb.shape[1]}x{rgb.shape[0]}")
        if p.pose_source == "topic":
            if pose.header.frame_id and pose.header.frame_id != p.map_frame:
                return self._warn("pose_frame", f"frame rejected: pose is in frame '{pose.header.frame_id}', "
                                  f"expected '{p.map_frame}' (parameter map_frame)")
            try:
                c2w = cv.pose_to_matrix(pose)
            except ValueError as exc:   # PoseError: NaN, inf, non-unit quaternion
                return self._warn("pose", f"frame rejected: bad pose on {p.pose_topic}: {exc}")
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
            self._camera = (frame.K, w, h, frame.cam_to_world, frame.frame_id, stamp_msg)
        if self.worker.submit(frame):
            self._warn("queue_drop", f"mapping is slower than the input: dropped the oldest queued frame "
                       f"(queue of {self.worker.queue.maxsize}, {self.worker.queue.dropped} dropped)", period=10.0)

    # ------------------------------------------------------------------------------ TF

    def _subscribe_tf(self, group) -> None:
        """/tf (volatile) and /tf_static (transient local: the latched statics), as tf2_ros listens."""
        try:
            from tf2_msgs.msg import TFMessage   # built from msg_tf2/ when no ROS 2 install provides it
        except ImportError as exc:
            if self.p.pose_source == "topic":   # poses come as PoseStamped: TF is not needed
                self.get_logger().warning(f"no tf2_msgs ({exc}): not listening to /tf (pose_source topic)")
                return
            raise RuntimeError(f"pose_source {self.p.pose_source} needs tf2_msgs (scripts/bootstrap.sh builds it "
                               f"from msg_tf2/): {exc}") from exc

        dyn = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        static = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(TFMessage, "/tf", lambda m: self._on_tf(m, False), dyn, callback_group=group)
        self.create_subscription(TFMessage, "/tf_static", lambda m: self._on_tf(m, True), static, callback_group=group)
        self.create_timer(0.05, self._try_pending, callback_group=group)

    def _on_tf(self, msg, static: bool) -> None:
        for ts in msg.transforms:
            tr = ts.transform
            try:
                self.tf.set_transform(ts.header.frame_id, ts.child_frame_id, cv.from_time(ts.header.stamp),
                                      [tr.translation.x, tr.translation.y, tr.translation.z],
                                      [tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w], static=static)
            except TFError as exc:
                self._warn("tf_input", f"transform refused ({'/tf_static' if static else '/tf'}): {exc}")
        if self._tf_pending:
            self._try_pending()

    def _pose_of(self, frame: Frame, pose_msg) -> np.ndarray:
        """cam_to_world of a frame from TF (pose_source tf) or odometry + TF; raises TFError / ValueError."""
        from rg_core.geometry.conventions import check_rigid

        p = self.p
        if not frame.frame_id:
            raise TFError("the colour image has an empty header.frame_id; TF needs its optical frame")
        if p.pose_source == "tf":
            return check_rigid(self.tf.lookup(p.map_frame, frame.frame_id, frame.stamp), "TF pose")
        from rg_core.io.rosbag import odometry_pose

        return odometry_pose(self.tf, p.map_frame, pose_msg, frame.frame_id, frame.stamp)

    def _try_pending(self) -> None:
        """Submit waiting frames whose transform is now known; drop those past their deadline."""
        with self._tf_lock:
            self._try_pending_locked()

    def _try_pending_locked(self) -> None:
        now = time.monotonic()
        keep = []
        for deadline, frame, extra in self._tf_pending:
            pose_msg, stamp_msg, w, h = extra
            try:
                frame.cam_to_world = self._pose_of(frame, pose_msg)
            except TFError as exc:
                if now < deadline and not _final(exc):
                    keep.append((deadline, frame, extra))
                else:
                    self._tf_drop(frame, pose_msg, str(exc))
                continue
            except ValueError as exc:   # PoseError: NaN / bad quaternion in the odometry
                self._warn("pose", f"frame rejected: bad pose on {self.p.odom_topic}: {exc}")
                continue
            self._submit(frame, stamp_msg, w, h)
        self._tf_pending = keep

    def _tf_drop(self, frame: Frame, pose_msg, why: str) -> None:
        self.tf_dropped += 1
        self._warn("tf", f"frame dropped: no transform '{self.p.map_frame}' <- '{frame.frame_id}' at "
                   f"t={frame.stamp:.6f} within {self.p.tf_wait:g} s: {why}")

    # ------------------------------------------------------------------------------ services

    def _on_ground(self, request, response):
        p = self.p
        query = request.query
        t = time.perf_counter()
        if not query.strip():
            result = GroundingResult(False, "empty query: say what to find, e.g. 'the red mug'")
        elif len(query) > p.max_query_chars:
            result = GroundingResult(False, f"query is {len(query)} characters, at most {p.max_query_chars} "
                                            "are accepted (parameter max_query_chars)")
        else:
            try:
                mode = cv.parse_mode(request.mode)
            except ValueError as exc:
                result = GroundingResult(False, str(exc), query=query)
            else:
                result = self.worker.ground(query, mode, int(request.max_results) or p.max_results, p.ground_timeout)
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
        response.success, response.message = True, "map reset: 0 keyframes, 0 Gaussians"
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------------------ output

    def _on_masks(self) -> None:
        with self._state_lock:
            result, cam = self._last_result, self._camera
        if result is None or cam is None or not result.objects:
            return
        K, w, h, c2w, frame_id, stamp = cam
        try:
            masks = self.worker.masks(result, K, c2w, w, h)
        except Exception as exc:  # noqa: BLE001
            return self._warn("masks", f"mask rendering failed: {type(exc).__name__}: {exc}")
        if masks is None:
            return
        amodal, visible = masks
        self.pub_amodal.publish(cv.mask_to_image(amodal, frame_id, stamp))
        self.pub_visible.publish(cv.mask_to_image(visible, frame_id, stamp))

    def _on_map_cloud(self) -> None:
        if self.pub_map_cloud.get_subscription_count() == 0:
            return
        snap = self.worker.snapshot(self.p.map_cloud_max_points)
        if snap is not None:
            self.pub_map_cloud.publish(to_pointcloud2(snap[0], snap[1], self.p.map_frame, self._stamp_now()))

    def status(self) -> dict:
        st = self.worker.stats()
        st["sync_dropped"] = sum(self.sync.dropped.values())
        st["input_errors"] = dict(self.input_errors)
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
            level, msg = DiagnosticStatus.WARN, f"no CameraInfo on {self.p.camera_info_topic}"
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


def spin(node: GroundingNode) -> int:
    """Spin `node` with a multi-threaded executor until SIGINT / shutdown; then stop it cleanly."""
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    executor = MultiThreadedExecutor(num_threads=6)
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.get_logger().info("shutting down")
        node.shutdown()
        executor.shutdown(timeout_sec=5)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
