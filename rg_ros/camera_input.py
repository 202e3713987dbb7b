"""The node's camera input: colour, depth and CameraInfo (and a pose topic) subscribed under
relative names (remapping, as in image_pipeline; a compressed transport subscribes to
<base>/<transport> as image_transport does), paired by the approximate time sync, checked,
converted into Frames and submitted to the map worker (now, or once TF has their pose)."""
from __future__ import annotations

import threading
import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from rg_core.geometry.tf_buffer import TFBuffer
from rg_core.io.ros_images import camera_info_K
from rg_core.io.ros_input import resolve_pose
from rg_core.io.sync import ApproximateTimeSync, SyncedSet

from . import convert as cv
from .frame_queue import Frame
from .params import QOS_OVERRIDES, NodeParams

class CameraInput:
    """Mixin of GroundingNode: the sensor subscriptions, the synchroniser and the frames they make.
    Uses the node's parameters (self.p), worker, _warn and TFInput (_subscribe_tf, _try_pending)."""

    def _make_inputs(self, p: NodeParams) -> None:
        """Subscriptions, the synchroniser, the TF buffer and the frames waiting for it."""
        self._last_info_time: float | None = None
        self._last_image_time: float | None = None
        self._first_image_time: float | None = None
        self._color_frame: str | None = None   # header.frame_id of the latest colour image (input_watch.py)
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
                                     callback_group=sensors, qos_overriding_options=QOS_OVERRIDES)
        # TF in its own group: processed alongside the images, never queued behind them (at one message
        # per topic and executor turn, /tf fell behind the images on a loaded CPU and frames timed out)
        self._subscribe_tf(MutuallyExclusiveCallbackGroup())

    def _transport_topic(self, base: str, transport: str) -> str:
        name = self.resolve_topic_name(base)
        return name if transport == "raw" else f"{name}/{transport}"

    def _on_msg(self, topic: str, msg) -> None:
        now = time.monotonic()
        self.msgs_in[topic] += 1
        if topic == "info":
            self._last_info_time = now
        elif topic == "color":
            if self._first_image_time is None:
                self._first_image_time = now
            self._last_image_time = now
            self._color_frame = msg.header.frame_id
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
