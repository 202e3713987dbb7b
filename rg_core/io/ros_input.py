"""ROS-style RGB-D input shared by the node and the bag reader: the input options, TF messages into a
TFBuffer, and a colour image's pose from TF, a PoseStamped or odometry chained with TF.

Messages are duck-typed (rosbags' or rclpy's classes alike). Errors are typed: TFError (and its
subclasses, see geometry.tf_buffer) when a transform is missing or refused, PoseError / ValueError
when the data is bad.
"""
from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from annotated_types import Interval

from ..config import check_fields, section
from ..geometry.conventions import PoseError, check_rigid
from ..geometry.rotations import checked_quat_to_rot
from ..geometry.tf_buffer import TFBuffer, TFError

POSE_SOURCES = ("tf", "topic", "odometry")
PoseSource = Literal["tf", "topic", "odometry"]


@section
class InputConfig:
    """Where poses come from and how colour, depth and CameraInfo are paired (node parameters and
    `rg map BAG` options of the same names)."""

    pose_source: PoseSource = "tf"
    """tf: map_frame <- the colour image's header.frame_id on /tf, /tf_static at its stamp; topic: a
    geometry_msgs/PoseStamped in map_frame; odometry: nav_msgs/Odometry chained with TF to the image's frame."""
    map_frame: str = "map"
    """Frame of poses, clouds and markers."""
    tf_wait: Annotated[float, Interval(ge=0.0, le=60.0)] = 0.5
    """Seconds a frame waits for its transform; then it is dropped and counted (diagnostics 'tf')."""
    tf_cache_time: Annotated[float, Interval(ge=0.1, le=3600.0)] = 10.0
    """Seconds of dynamic TF history kept (a bag keeps all of its own)."""
    tf_max_gap: Annotated[float, Interval(ge=0.0, le=3600.0)] = 0.5
    """A dynamic TF link is not interpolated across a longer gap between samples (s); 0 = any gap, as tf2."""
    tf_extrapolation: Annotated[float, Interval(ge=0.0, le=60.0)] = 0.0
    """Seconds past a link's newest (or before its oldest) sample where its nearest sample is used (tf2: 0)."""
    sync_queue_size: Annotated[int, Interval(ge=1, le=1000)] = 10
    """Messages per input kept by the approximate time synchroniser."""
    sync_slop: Annotated[float, Interval(ge=0.0, le=10.0)] = 0.05
    """Largest stamp spread (s) of one synchronised colour/depth/info set; a set whose stamps differ
    goes out once every input has a message past it (equal stamps: at once)."""

    def __post_init__(self):
        check_fields(self)


def from_time(stamp) -> float:
    """builtin_interfaces/Time -> seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def stamp_of(msg) -> float:
    """header.stamp of a message (or a TransformStamped) in seconds."""
    return from_time(msg.header.stamp)


def transform_to_matrix(tr) -> np.ndarray:
    """geometry_msgs/Transform or Pose -> [4, 4]; PoseError on NaN / bad quaternion."""
    field, t, r = (("position", tr.position, tr.orientation) if hasattr(tr, "position")
                   else ("translation", tr.translation, tr.rotation))
    v = np.array([t.x, t.y, t.z], np.float64)
    if not np.isfinite(v).all():
        raise PoseError(f"{field} contains NaN or inf: {v.tolist()}")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = checked_quat_to_rot([r.x, r.y, r.z, r.w]), v
    return T


def add_tf_message(buf: TFBuffer, msg, static: bool) -> list[str]:
    """Every TransformStamped of a TFMessage into `buf`; returns the errors of refused ones."""
    errors = []
    for ts in msg.transforms:
        tr = ts.transform
        try:
            buf.set_transform(ts.header.frame_id, ts.child_frame_id, stamp_of(ts),
                              [tr.translation.x, tr.translation.y, tr.translation.z],
                              [tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w], static=static)
        except TFError as exc:
            errors.append(str(exc))
    return errors


def resolve_pose(buf: TFBuffer, opts: InputConfig, cam_frame: str, t: float, pose_msg=None) -> np.ndarray:
    """cam_to_world [4, 4] (OpenCV axes = the optical frame's) of a colour image with header.frame_id
    `cam_frame` at stamp t, by opts.pose_source; `pose_msg` is the paired PoseStamped or Odometry."""
    if opts.pose_source == "topic":
        frame = pose_msg.header.frame_id.lstrip("/")
        if frame and frame != opts.map_frame.lstrip("/"):
            raise ValueError(f"pose is in frame '{pose_msg.header.frame_id}', expected '{opts.map_frame}' "
                             "(map_frame)")
        return transform_to_matrix(pose_msg.pose)
    if not cam_frame:
        raise TFError("the colour image has an empty header.frame_id; TF needs its optical frame")
    if opts.pose_source == "tf":
        return check_rigid(buf.lookup(opts.map_frame, cam_frame, t), f"TF {opts.map_frame} <- {cam_frame}")
    return odometry_pose(buf, opts.map_frame, pose_msg, cam_frame, t)


def odometry_pose(buf: TFBuffer, map_frame: str, odom, cam_frame: str, t: float) -> np.ndarray:
    """map <- camera from nav_msgs/Odometry (odom frame <- child) chained with TF where frames differ."""
    T_oc = transform_to_matrix(odom.pose.pose)   # header.frame_id <- child_frame_id
    parent, child = odom.header.frame_id.lstrip("/"), odom.child_frame_id.lstrip("/")
    T_mo = np.eye(4) if parent == map_frame.lstrip("/") else buf.lookup(map_frame, parent, t)
    T_cc = np.eye(4) if (not cam_frame or child == cam_frame.lstrip("/")) else buf.lookup(child, cam_frame, t)
    return check_rigid(T_mo @ T_oc @ T_cc, "odometry pose")
