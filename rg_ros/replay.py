"""`rg-replay`: a scene folder published as a camera driver would (SCENE: rgb8, 16UC1 depth,
CameraInfo, PoseStamped and /tf, one stamp per frame), or a ROS 2 bag played on its recorded topics
(BAG: .mcap, .db3 or a rosbag2 folder; the pip-install stand-in for `ros2 bag play`).

A bag's first pass publishes the recorded CDR bytes unchanged; timing follows the recorded log
times divided by --rate; with --loop every later pass shifts the header stamps (and each
TransformStamped's) by the bag's duration so stamps keep increasing; /tf_static is sent once,
latched. Everything is published reliable, depth 100: best-effort (SensorDataQoS) subscribers accept
it, reliable ones get every message. Publishing starts once every topic has its subscribers (DDS
discovery is asymmetric: the settle time lets the subscribers' side catch up) and ends once reliable
subscribers acknowledged everything (bounded), instead of fixed sleeps.
"""
from __future__ import annotations

import importlib
import json
import sys
import time
from pathlib import Path


def replay_qos(latched: bool = False):
    """What rg-replay publishes with: reliable, depth 100 (volatile, or transient local for /tf_static).
    Best-effort (SensorDataQoS) subscribers accept it and may lose messages; a subscriber overridden to
    reliable (qos_overrides) with a deep enough history gets every one."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def wait_for_subscribers(pubs: list, timeout: float, settle: float = 0.5, minimum: int = 1) -> list[str]:
    """Wait up to `timeout` s until every publisher in `pubs` has at least `minimum` subscriptions,
    then `settle` s more for the subscribers' side of discovery. Returns the topics still short of
    subscribers (empty when all matched)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and any(p.get_subscription_count() < minimum for p in pubs):
        time.sleep(0.05)
    short = [p.topic_name for p in pubs if p.get_subscription_count() < minimum]
    if not short and timeout > 0:
        time.sleep(settle)
    return short


def report_unmatched(log, short: list[str], timeout: float, minimum: int) -> None:
    """Say which topics nobody listens to (their messages go nowhere), as `ros2 bag play` users expect."""
    if short:
        log.warning(f"after {timeout:g} s, fewer than {minimum} subscriber(s) on {', '.join(short)}: "
                    "their messages go nowhere (is the node running, with matching names and domain?)")


def flush_publishers(pubs: list, timeout: float = 3.0) -> bool:
    """Wait (at most `timeout` s in all) until every reliable subscriber acknowledged what was
    published; best-effort subscribers acknowledge nothing and are not waited for."""
    from rclpy.duration import Duration

    t_end = time.monotonic() + timeout
    ok = True
    for p in pubs:
        left = max(0.0, t_end - time.monotonic())
        try:
            ok = bool(p.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))) and ok
        except Exception:  # noqa: BLE001 - an RMW without the call: fall back to a short grace period
            time.sleep(0.3)
            return False
    time.sleep(0.1)   # the last datagrams leave the socket
    return ok


def message_class(msgtype: str):
    """'sensor_msgs/msg/Image' -> sensor_msgs.msg.Image (ImportError names what is missing)."""
    pkg, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ImportError, AttributeError) as exc:
        raise ImportError(f"no Python type for {msgtype} ({exc}); install its ROS 2 interface package") from exc


def _shift(msg, dt_ns: int) -> None:
    """Add dt_ns to every header stamp of a rosbags message (and of each TransformStamped)."""
    def bump(stamp):
        total = stamp.sec * 1_000_000_000 + stamp.nanosec + dt_ns
        stamp.sec, stamp.nanosec = divmod(total, 1_000_000_000)

    if hasattr(msg, "header"):
        bump(msg.header.stamp)
    for ts in getattr(msg, "transforms", ()) or ():
        bump(ts.header.stamp)


def replay_bag(args, ros_argv: list[str]) -> int:
    from rg_core.io.images import SceneError
    from rg_core.io.rosbag import open_reader

    path = Path(args.scene)
    try:
        reader = open_reader(path)
    except SceneError as exc:
        print(f"rg-replay: {exc}", file=sys.stderr)
        return 2
    import rclpy

    try:
        conns = [c for c in reader.connections if args.topics is None or c.topic in args.topics]
        if not conns:
            print(f"rg-replay: {path}: none of the topics {args.topics} is in the bag "
                  f"({', '.join(sorted({c.topic for c in reader.connections}))})", file=sys.stderr)
            return 2
        try:
            classes = {c.topic: message_class(c.msgtype) for c in conns}
        except ImportError as exc:
            print(f"rg-replay: {exc}", file=sys.stderr)
            return 2
        rclpy.init(args=ros_argv)
        node = rclpy.create_node("rg_replay")
        pubs = {}
        for c in conns:
            latched = c.topic.rstrip("/").endswith("tf_static")
            pubs[c.topic] = node.create_publisher(classes[c.topic], c.topic, replay_qos(latched))
        log = node.get_logger()
        sent, counter = 0, {"passes": 0}
        report_unmatched(log, wait_for_subscribers(list(pubs.values()), args.wait, minimum=args.min_subscribers),
                         args.wait, args.min_subscribers)
        try:
            for topic, raw in _bag_stream(reader, path, conns, args, counter):
                pubs[topic].publish(raw)
                sent += 1
        except KeyboardInterrupt:
            pass
        except SceneError as exc:
            print(f"rg-replay: {exc}", file=sys.stderr)
            return 2
        finally:
            log.info(f"published {sent} messages from {path} ({counter['passes']} passes)")
            flush_publishers(list(pubs.values()))
            node.destroy_node()
            rclpy.try_shutdown()
    finally:
        reader.close()
    return 0


def _bag_stream(reader, path, conns, args, counter: dict):
    """(topic, CDR bytes) at the recorded times divided by --rate; with --loop pass after pass, each
    later pass with its stamps shifted by the bag's duration and without /tf_static (latched once);
    at most --count messages. counter["passes"] counts the passes begun."""
    speed, duration_ns, sent = args.rate or 1.0, max(reader.duration, 1), 0
    while True:
        shift = counter["passes"] * duration_ns
        counter["passes"] += 1
        wall0, bag0 = time.monotonic(), None
        for conn, t, raw, msg in _messages(reader, path, conns, deserialize=shift > 0):
            if shift and conn.topic.rstrip("/").endswith("tf_static"):
                continue
            bag0 = t if bag0 is None else bag0
            delay = (t - bag0) * 1e-9 / speed - (time.monotonic() - wall0)
            if delay > 0:
                time.sleep(delay)
            if shift:
                _shift(msg, shift)
                raw = reader.typestore.serialize_cdr(msg, conn.msgtype)
            yield conn.topic, bytes(raw)
            sent += 1
            if args.count and sent >= args.count:
                return
        if not args.loop:
            return


def _messages(reader, path, conns, deserialize: bool):
    """(connection, log time ns, raw CDR, message or None) in log-time order."""
    if deserialize:
        from rg_core.io.rosbag import iter_messages

        for conn, t, msg in iter_messages(reader, path, conns):
            yield conn, t, None, msg
        return
    from rg_core.io.rosbag import iter_raw

    for conn, t, raw in iter_raw(reader, path, conns):
        yield conn, t, raw, None


def replay_scene(args, ros_argv: list[str]) -> int:
    """Publish a scene folder's frames at args.rate Hz (rg-replay SCENE)."""
    from rg_core.io.captures import read_scene
    from rg_core.io.images import SceneError

    args.rate = args.rate or 2.0

    try:
        scene = read_scene(args.scene)
    except SceneError as exc:
        print(f"rg-replay: {exc}", file=sys.stderr)
        return 2
    frames = {"train": scene.train, "test": scene.test, "all": sorted(scene.train + scene.test,
                                                                         key=lambda f: f.stamp)}[args.split]
    if not frames:
        print(f"rg-replay: {args.scene} has no {args.split} frames", file=sys.stderr)
        return 2
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.duration import Duration
    from sensor_msgs.msg import CameraInfo, Image

    rclpy.init(args=ros_argv)
    node = rclpy.create_node("rg_replay")
    qos = replay_qos()
    pubs = [node.create_publisher(Image, args.color_topic, qos), node.create_publisher(Image, args.depth_topic, qos),
            node.create_publisher(CameraInfo, args.camera_info_topic, qos),
            node.create_publisher(PoseStamped, args.pose_topic, qos)]
    tf_pub = _tf_publisher(node)   # the same pose on /tf (map -> optical frame) for pose_source tf
    log = node.get_logger()
    sent = 0
    faults = Faults(getattr(args, "faults", 0))
    try:
        report_unmatched(log, wait_for_subscribers(pubs + ([tf_pub] if tf_pub else []), args.wait,
                                                   minimum=args.min_subscribers), args.wait, args.min_subscribers)
        for f, lag in _paced(frames, args, faults):
            stamp = node.get_clock().now() - Duration(nanoseconds=int(lag * 1e9))   # its capture time
            msgs = frame_messages(f, stamp.to_msg(), args.frame_id, args.map_frame)
            with_pose = faults.next(msgs[3])
            for pub, msg in zip(pubs, msgs if with_pose else msgs[:3]):
                pub.publish(msg)
            if tf_pub is not None and with_pose:
                tf_pub.publish(_pose_to_tf(msgs[3], args.frame_id))
            sent += 1
    except KeyboardInterrupt:
        pass
    finally:
        log.info(f"published {sent} frames from {args.scene}" + (f"; faults injected: {json.dumps(faults.counts)}"
                                                                  if faults.every else ""))
        flush_publishers(pubs + ([tf_pub] if tf_pub is not None else []))
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


class Faults:
    """--faults N: after every N frames the next fault, in turn: a frame whose pose is not a rotation
    (quaternion 0, 0, 0, 0), a pose/TF gap (the next GAP frames without pose or TF), a burst (a
    stalled link: nothing for BURST frame periods, then the BURST frames captured meanwhile at once,
    each stamped with its capture time, see _paced). `counts` says how many of each were injected."""

    KINDS = ("bad_pose", "tf_gap", "burst")
    GAP, BURST = 10, 100

    def __init__(self, every: int):
        self.every, self.i, self.gap, self.burst = max(0, int(every or 0)), 0, 0, 0
        self.counts = dict.fromkeys(self.KINDS, 0)

    def next(self, pose) -> bool:
        """Apply this frame's fault to `pose` (PoseStamped, in place); False: send it without pose or TF."""
        self.i += 1
        if self.gap:
            self.gap -= 1
            return False
        if not self.every or self.i % self.every:
            return True
        kind = self.KINDS[sum(self.counts.values()) % len(self.KINDS)]
        self.counts[kind] += 1
        if kind == "bad_pose":
            q = pose.pose.orientation
            q.x = q.y = q.z = q.w = 0.0
        elif kind == "tf_gap":
            self.gap = self.GAP
        else:
            self.burst = self.BURST
        return True


def _paced(frames: list, args, faults: Faults | None = None):
    """Yield (frame, lag s) at args.rate Hz, once or forever (--loop), at most --count of them. lag:
    how long before it is sent the frame was captured (its stamp is now - lag): 0, except in a
    fault burst, which waits faults.BURST frame periods (the stall) and then sends the frames of
    that time at once, each with its capture stamp, as a camera's frames held up by a link arrive."""
    next_t, sent = time.monotonic(), 0
    while True:
        for f in frames:
            lag = 0.0
            if faults is not None and faults.burst:
                if faults.burst == faults.BURST:
                    time.sleep(faults.BURST / args.rate)   # the stall
                faults.burst -= 1
                lag = faults.burst / args.rate
                next_t = time.monotonic()
            yield f, lag
            sent += 1
            if args.count and sent >= args.count:
                return
            if faults is not None and faults.burst:
                continue   # the rest of a burst (or the stall before it) follows at once
            next_t += 1.0 / args.rate
            time.sleep(max(0.0, next_t - time.monotonic()))
        if not args.loop:
            return


def frame_messages(frame, stamp, frame_id: str, map_frame: str):
    """One scene frame -> (Image rgb8, Image 16UC1 mm, CameraInfo, PoseStamped), all with `stamp`."""
    import numpy as np
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo

    from . import convert as cv

    rgb = frame.load_rgb()
    depth = frame.load_depth()
    mm = np.where(np.isfinite(depth) & (depth > 0), np.round(depth * 1000.0), 0).clip(0, 65535).astype(np.uint16)
    hdr = cv.header(frame_id, stamp)
    color = cv.to_image(rgb, "rgb8")
    color.header = hdr
    dimg = cv.to_image(mm, "16UC1")
    dimg.header = hdr
    K = np.asarray(frame.intrinsics.K, np.float64)
    h, w = rgb.shape[:2]
    info = CameraInfo(header=hdr, width=w, height=h, distortion_model="plumb_bob", d=[0.0] * 5,
                      k=K.reshape(-1).tolist(), r=np.eye(3).reshape(-1).tolist(),
                      p=np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist())
    pose = PoseStamped(header=cv.header(map_frame, stamp), pose=cv.matrix_to_pose(frame.cam_to_world))
    return color, dimg, info, pose


def _tf_publisher(node):
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return node.create_publisher(TFMessage, "/tf", replay_qos())


def _pose_to_tf(pose, child: str):
    """PoseStamped (of `child` in the pose's frame) -> TFMessage with one TransformStamped."""
    from geometry_msgs.msg import Transform, TransformStamped, Vector3
    from tf2_msgs.msg import TFMessage

    p = pose.pose.position
    tr = Transform(translation=Vector3(x=p.x, y=p.y, z=p.z), rotation=pose.pose.orientation)
    return TFMessage(transforms=[TransformStamped(header=pose.header, child_frame_id=child, transform=tr)])
