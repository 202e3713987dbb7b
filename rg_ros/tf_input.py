"""The node's poses from TF (and odometry + TF): /tf and /tf_static into the node's TFBuffer, and
frames waiting for their transform, submitted when it comes or dropped (and counted) when it
cannot come in time. A mixin of GroundingNode: it uses the node's parameters (self.p), buffer
(self.tf), pending list and _submit/_warn."""
from __future__ import annotations

import time

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from rg_core.geometry.tf_buffer import GapError, LoopError, PastExtrapolationError, TFError
from rg_core.io.ros_input import add_tf_message, resolve_pose

from .frame_queue import Frame


def _final(exc: TFError) -> bool:
    """A lookup error that waiting cannot cure: data already past the stamp (a gap, the past) or a loop."""
    return isinstance(exc, (LoopError, GapError, PastExtrapolationError))


class TFInput:
    """Mixin of GroundingNode: TF subscriptions and the frames waiting for their transform."""

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
        for err in add_tf_message(self.tf, msg, static):
            self._warn("tf_input", f"transform refused ({'/tf_static' if static else '/tf'}): {err}")
        if self._tf_pending:
            self._try_pending()

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
                frame.cam_to_world = resolve_pose(self.tf, self.inputs, frame.frame_id, frame.stamp, pose_msg)
            except TFError as exc:
                if now < deadline and not _final(exc):
                    keep.append((deadline, frame, extra))
                else:
                    self._tf_drop(frame, pose_msg, str(exc))
                continue
            except ValueError as exc:   # PoseError: NaN / bad quaternion in the odometry
                self._warn("pose", f"frame rejected: bad pose on {self.topics['pose']}: {exc}")
                continue
            self._submit(frame, stamp_msg, w, h)
        self._tf_pending = keep

    def _tf_drop(self, frame: Frame, pose_msg, why: str) -> None:
        self.tf_dropped += 1
        self._warn("tf", f"frame dropped: no transform '{self.p.map_frame}' <- '{frame.frame_id}' at "
                   f"t={frame.stamp:.6f} within {self.p.tf_wait:g} s: {why}")
