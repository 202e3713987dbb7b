"""`rg-replay BAG`: play a ROS 2 bag (.mcap, .db3 or a rosbag2 folder) on its recorded topics, the
pip-install stand-in for `ros2 bag play` (rosbag2's player is not on PyPI).

The first pass publishes the recorded CDR bytes unchanged (recorded header stamps, no
re-serialisation). Timing follows the recorded log times divided by --rate (a speed factor).
With --loop, every later pass shifts all header stamps (and each TransformStamped's in /tf) by the
bag's duration so stamps keep increasing, as a live robot's would; /tf_static is sent once. The
publishers use the QoS recorded in the bag where it matters: /tf_static transient local (latched),
everything else reliable with depth 100, which best-effort (SensorDataQoS) subscribers accept.
"""
from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

from .publish_util import replay_qos, flush_publishers, report_unmatched, wait_for_subscribers


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

    speed = args.rate or 1.0
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
        sent = passes = 0
        report_unmatched(log, wait_for_subscribers(list(pubs.values()), args.wait, minimum=args.min_subscribers),
                         args.wait, args.min_subscribers)
        duration_ns = max(reader.duration, 1)
        try:
            while True:
                shift = passes * duration_ns
                passes += 1
                wall0, bag0 = time.monotonic(), None
                for conn, t, raw, msg in _messages(reader, path, conns, deserialize=shift > 0):
                    if shift and conn.topic.rstrip("/").endswith("tf_static"):
                        continue   # latched once is enough
                    bag0 = t if bag0 is None else bag0
                    delay = (t - bag0) * 1e-9 / speed - (time.monotonic() - wall0)
                    if delay > 0:
                        time.sleep(delay)
                    if shift:
                        _shift(msg, shift)
                        raw = reader.typestore.serialize_cdr(msg, conn.msgtype)
                    pubs[conn.topic].publish(bytes(raw))
                    sent += 1
                    if args.count and sent >= args.count:
                        raise StopIteration
                if not args.loop:
                    break
        except (StopIteration, KeyboardInterrupt):
            pass
        except SceneError as exc:
            print(f"rg-replay: {exc}", file=sys.stderr)
            return 2
        finally:
            log.info(f"published {sent} messages from {path} ({passes} passes)")
            flush_publishers(list(pubs.values()))
            node.destroy_node()
            rclpy.try_shutdown()
    finally:
        reader.close()
    return 0


def _messages(reader, path, conns, deserialize: bool):
    """(connection, log time ns, raw CDR, message or None) in log-time order."""
    if deserialize:
        from rg_core.io.rosbag import iter_messages

        for conn, t, msg in iter_messages(reader, path, conns):
            yield conn, t, None, msg
        return
    from rg_core.io.images import SceneError

    it = reader.messages(connections=conns)
    while True:
        try:
            conn, t, raw = next(it)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - a truncated bag
            raise SceneError(f"{path}: reading the bag failed ({type(exc).__name__}: {exc}); is it truncated?") \
                from exc
        yield conn, t, raw, None
