"""ROS 2 bags (rosbag2: .mcap, .db3 or a bag folder with metadata.yaml) as scenes, headless.

Reads through the `rosbags` library (pure Python; its CDR deserialiser, no ROS install). A bag
becomes a Scene whose frames decode their images on demand (memory holds the messages, compressed
when the bag is):

- topics: colour (sensor_msgs/Image or CompressedImage), depth (Image 16UC1/32FC1 or
  compressedDepth), CameraInfo, /tf + /tf_static, and a PoseStamped or nav_msgs/Odometry topic for
  the other pose sources; each is an option, auto-detected when empty (errors list the candidates);
- colour, depth and CameraInfo (and the pose message for pose_source topic/odometry) are paired by
  header stamp with the node's approximate time synchroniser, in the bag's order;
- poses: `tf` (default) looks up map_frame <- the colour image's header.frame_id (its optical
  frame) at the colour stamp in a TFBuffer holding all of the bag's transforms; `topic` takes a
  PoseStamped of the optical frame in map_frame; `odometry` takes a nav_msgs/Odometry (pose of its
  child frame) and chains it with TF to the optical frame (and to map_frame when the odometry's
  frame differs from it);
- frames without a pose (TF missing, a bad CameraInfo, ...) are dropped and counted per reason in
  `scene.info["dropped"]`; a bag that yields no frame is an error saying why.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import section
from ..geometry.tf_buffer import TFBuffer, TFError
from . import ros_images
from .ros_input import InputConfig, add_tf_message, resolve_pose, stamp_of
from .images import SceneError
from .scene import Frame, Intrinsics, Scene
from .sync import ApproximateTimeSync

BAG_SUFFIXES = (".mcap", ".db3")
T_IMAGE = "sensor_msgs/msg/Image"
T_COMPRESSED = "sensor_msgs/msg/CompressedImage"
T_INFO = "sensor_msgs/msg/CameraInfo"
T_TF = "tf2_msgs/msg/TFMessage"
T_POSE = "geometry_msgs/msg/PoseStamped"
T_ODOM = "nav_msgs/msg/Odometry"


@section
class BagOptions(InputConfig):
    """How a bag is read (`rg map BAG` options): the topics, empty = auto-detected, and the input
    options the node has too."""

    color_topic: str = ""
    """Image or CompressedImage (jpeg/png)."""
    depth_topic: str = ""
    """Image 16UC1/32FC1 or CompressedImage compressedDepth, registered to colour."""
    camera_info_topic: str = ""
    """CameraInfo of the colour camera (auto: next to the colour topic)."""
    pose_topic: str = ""
    """PoseStamped (pose_source topic) or Odometry (odometry) topic."""


def is_bag(path: str | Path) -> bool:
    """A .mcap/.db3 file or a rosbag2 folder (metadata.yaml)."""
    p = Path(path)
    return (p.is_file() and p.suffix in BAG_SUFFIXES) or (p.is_dir() and (p / "metadata.yaml").is_file())


# ------------------------------------------------------------------------------ topic detection

def _pick(kind: str, cands: list[str], prefer) -> str:
    if not cands:
        raise SceneError(f"no {kind} topic in the bag")
    if len(cands) == 1:
        return cands[0]
    scored = sorted(cands, key=lambda t: (-prefer(t), t))
    if prefer(scored[0]) > prefer(scored[1]):
        return scored[0]
    raise SceneError(f"several {kind} topics could be meant: {', '.join(sorted(cands))}; name one with the "
                     f"{kind.replace(' ', '_')}_topic option")


def _base(topic: str) -> str:
    """Topic without its image_transport suffix and image name: /cam/color/image_raw/compressed -> /cam/color."""
    parts = topic.rstrip("/").split("/")
    if parts[-1] in ("compressed", "compressedDepth", "theora", "zstd"):
        parts = parts[:-1]
    if parts and parts[-1].startswith("image"):
        parts = parts[:-1]
    return "/".join(parts)


def detect_topics(types: dict[str, str], opts: BagOptions) -> dict[str, str]:
    """{role: topic} for color, depth, info, tf, tf_static, pose (empty where not present/needed)."""
    def of(*kinds):
        return [t for t, k in types.items() if k in kinds]

    def need(topic: str, role: str, kinds) -> str:
        if topic not in types:
            raise SceneError(f"{role} topic '{topic}' is not in the bag; its topics: "
                             + ", ".join(f"{t} [{k}]" for t, k in sorted(types.items())))
        if types[topic] not in kinds:
            raise SceneError(f"{role} topic '{topic}' has type {types[topic]}, expected {' or '.join(kinds)}")
        return topic

    imgs = of(T_IMAGE, T_COMPRESSED)

    def is_depth(t):
        return "depth" in t.lower() or t.endswith("/compressedDepth")

    out = {}
    if opts.color_topic:
        out["color"] = need(opts.color_topic, "colour", (T_IMAGE, T_COMPRESSED))
    else:
        cands = [t for t in imgs if not is_depth(t) and not t.endswith("/compressedDepth")]
        out["color"] = _pick("color", cands, lambda t: (("color" in t or "rgb" in t or "colour" in t) * 2
                                                         + (types[t] == T_IMAGE)))
    if opts.depth_topic:
        out["depth"] = need(opts.depth_topic, "depth", (T_IMAGE, T_COMPRESSED))
    else:
        cands = [t for t in imgs if is_depth(t) and not (types[t] == T_COMPRESSED
                                                          and not t.endswith("/compressedDepth"))]
        out["depth"] = _pick("depth", cands, lambda t: (("aligned" in t or "registered" in t) * 2
                                                         + (types[t] == T_IMAGE)))
    if opts.camera_info_topic:
        out["info"] = need(opts.camera_info_topic, "camera_info", (T_INFO,))
    else:
        cands = of(T_INFO)
        base = _base(out["color"])
        out["info"] = _pick("camera info", cands, lambda t: (_base(t) == base) * 2 + ("color" in t))
    tfs = of(T_TF)
    out["tf_static"] = [t for t in tfs if t.rstrip("/").endswith("tf_static")]
    out["tf"] = [t for t in tfs if t not in out["tf_static"]]
    if opts.pose_source == "tf" and not tfs:
        raise SceneError("pose_source tf: the bag has no tf2_msgs/TFMessage topic (/tf, /tf_static); "
                         "use pose_source topic or odometry")
    if opts.pose_source in ("topic", "odometry"):
        kind = T_POSE if opts.pose_source == "topic" else T_ODOM
        if opts.pose_topic:
            out["pose"] = need(opts.pose_topic, "pose", (kind,))
        elif not of(kind):
            raise SceneError(f"pose_source {opts.pose_source}: no {kind} topic in the bag (pose_topic option)")
        else:
            out["pose"] = _pick("pose", of(kind), lambda t: 0)
    return out


# ------------------------------------------------------------------------------ frames

@dataclass
class BagFrame(Frame):
    """A frame whose colour and depth are messages from a bag, decoded when loaded."""

    color_msg: object = None
    depth_msg: object = None
    where: str = ""

    def load_rgb(self) -> np.ndarray:  # [H, W, 3] uint8
        return self._decode(ros_images.decode_color, self.color_msg, "colour", self.image_path)

    def load_depth(self) -> np.ndarray:  # [H, W] float32 metres
        return self._decode(ros_images.decode_depth, self.depth_msg, "depth", self.depth_path)

    def _decode(self, decode, msg, what: str, path: Path) -> np.ndarray:
        try:
            img = decode(msg)
        except ValueError as exc:
            raise SceneError(f"{self.where}: {what} image: {exc}") from exc
        self._check_size(img, path)
        return img


def _check_encodings(msg, role: str, topic: str) -> None:
    """Refuse an unsupported encoding before mapping starts (the first message of each stream)."""
    if hasattr(msg, "format"):
        fmt = msg.format.lower()
        ok = ("compresseddepth" in fmt and fmt.split(";")[0].strip().upper() in ros_images.DEPTH_ENCODINGS) \
            if role == "depth" else (not fmt or any(k in fmt for k in ("jpeg", "jpg", "png"))) and \
            "compresseddepth" not in fmt
        if not ok:
            want = "'16UC1; compressedDepth png' or '32FC1; compressedDepth png'" if role == "depth" else "jpeg or png"
            raise SceneError(f"{topic}: CompressedImage format '{msg.format}' is not supported for {role}; "
                             f"supported: {want}")
    else:
        allowed = ros_images.DEPTH_ENCODINGS if role == "depth" else ros_images.COLOR_ENCODINGS + ("mono8",)
        if msg.encoding not in allowed:
            raise SceneError(f"{topic}: Image encoding '{msg.encoding}' is not supported for {role}; "
                             f"supported: {', '.join(allowed)}")


class _Drops:
    def __init__(self):
        self.counts: dict[str, int] = {}
        self.examples: dict[str, str] = {}

    def add(self, reason: str, detail: str) -> None:
        self.counts[reason] = self.counts.get(reason, 0) + 1
        self.examples.setdefault(reason, detail)


def open_reader(path: Path):
    """An opened rosbags AnyReader; SceneError for a missing, unreadable or truncated bag."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:   # pragma: no cover - rosbags is in requirements.txt
        raise SceneError(f"{path}: reading bags needs the 'rosbags' package (pip install -r requirements.txt)") from exc
    if not path.exists():
        raise SceneError(f"{path}: bag not found")
    reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_KILTED))
    try:
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds; all mean "cannot read it"
        raise SceneError(f"{path}: cannot open the bag ({type(exc).__name__}: {exc}); truncated or not a "
                         "rosbag2 (.mcap, .db3 or a folder with metadata.yaml)?") from exc
    return reader


def iter_raw(reader, path: Path, connections):
    """(connection, log time ns, raw CDR bytes), with read errors (a truncated bag) as SceneError."""
    it = reader.messages(connections=connections)
    while True:
        try:
            conn, t, raw = next(it)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001
            raise SceneError(f"{path}: reading the bag failed ({type(exc).__name__}: {exc}); is it truncated?") \
                from exc
        yield conn, t, raw


def iter_messages(reader, path: Path, connections):
    """(connection, log time ns, deserialised message), with read errors as SceneError."""
    for conn, t, raw in iter_raw(reader, path, connections):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001
            raise SceneError(f"{path}: a {conn.msgtype} message on {conn.topic} cannot be deserialised "
                             f"({type(exc).__name__}: {exc}); truncated or corrupt bag?") from exc
        yield conn, t, msg


def read_bag(path: str | Path, opts: BagOptions | None = None, test_every: int = 8) -> Scene:
    """A rosbag2 as a Scene (every `test_every`-th paired frame is a test view, as read_capture does).
    `scene.info` holds the topics used, frame counts and dropped frames per reason."""
    opts = opts or BagOptions()
    path = Path(path)
    reader = open_reader(path)
    try:
        types = {c.topic: c.msgtype for c in reader.connections}
        topics = detect_topics(types, opts)
        duration = max(reader.duration * 1e-9, 1.0)
        buf = TFBuffer(cache_time=duration + 1.0, extrapolation_limit=opts.tf_extrapolation, max_gap=opts.tf_max_gap)
        drops = _Drops()
        tf_errors: list[str] = []
        # pass 1: all transforms (a frame may come before the transform that places it)
        tf_topics = topics["tf"] + topics["tf_static"]
        conns = [c for c in reader.connections if c.topic in tf_topics]
        if conns:
            for conn, _, msg in iter_messages(reader, path, conns):
                tf_errors += add_tf_message(buf, msg, static=conn.topic in topics["tf_static"])
        # pass 2: pair colour, depth, info (and pose) by stamp
        roles = ["color", "depth", "info"] + (["pose"] if "pose" in topics else [])
        by_topic = {}
        for r in roles:
            by_topic.setdefault(topics[r], []).append(r)
        sets = []
        sync = ApproximateTimeSync(tuple(roles), opts.sync_queue_size, opts.sync_slop, callback=sets.append)
        checked: set[str] = set()
        counts = {r: 0 for r in roles}
        conns = [c for c in reader.connections if c.topic in by_topic]
        for conn, _, msg in iter_messages(reader, path, conns):
            for role in by_topic[conn.topic]:
                counts[role] += 1
                if role in ("color", "depth") and role not in checked:
                    _check_encodings(msg, role, conn.topic)
                    checked.add(role)
                try:
                    sync.add(role, stamp_of(msg), msg)
                except ValueError as exc:
                    drops.add(f"{role}_stamp", str(exc))
        sync.flush()   # the bag's last sets: no later message will make them final
        frames = []
        for s in sets:
            color, depth, info = s.msgs[:3]
            t = s.stamps[0]
            where = f"{path.name}: {topics['color']} at t={t:.6f}"
            try:
                K, (w, h) = ros_images.camera_info_K(info)
            except ValueError as exc:
                drops.add("camera_info", f"{where}: {exc}")
                continue
            intr = Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), w, h)
            try:
                c2w = resolve_pose(buf, opts, color.header.frame_id, t, s.msgs[3] if len(s.msgs) > 3 else None)
            except TFError as exc:
                drops.add("tf", f"{where}: {exc}")
                continue
            except ValueError as exc:   # PoseError too
                drops.add("pose", f"{where}: {exc}")
                continue
            frames.append(BagFrame(index=len(frames), intrinsics=intr, cam_to_world=c2w,
                                   image_path=Path(f"{path.name}:{topics['color']}@{t:.6f}"),
                                   depth_path=Path(f"{path.name}:{topics['depth']}@{t:.6f}"),
                                   depth_scale=1.0, stamp=t, color_msg=color, depth_msg=depth, where=where))
        sync_dropped = sync.dropped
    finally:
        reader.close()
    info = {"bag": str(path), "topics": topics, "pose_source": opts.pose_source, "map_frame": opts.map_frame,
            "messages": counts, "paired": len(sets), "frames": len(frames),
            "dropped": dict(drops.counts), "dropped_examples": dict(drops.examples),
            "sync_dropped": {k: v for k, v in sync_dropped.items() if v}, "sync_mixed": sync.mixed,
            "tf_rejected": len(tf_errors),
            "tf_rejected_examples": tf_errors[:3]}
    if not frames:
        why = "; ".join(f"{k} x{v}: {drops.examples[k]}" for k, v in drops.counts.items()) or \
              f"no colour/depth/camera_info set within {opts.sync_slop} s (messages per role: {counts})"
        raise SceneError(f"{path}: no usable frame in the bag ({why})")
    train = [f for i, f in enumerate(frames) if test_every <= 0 or i % test_every != 0]
    test = [f for i, f in enumerate(frames) if test_every > 0 and i % test_every == 0]
    return BagScene(root=path, train=train, test=test, kind="rosbag2", info=info)


@dataclass
class BagScene(Scene):
    info: dict = field(default_factory=dict)
