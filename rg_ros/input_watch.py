"""Inputs that never arrive are reported: when no frame reached the map for `input_timeout` s the
node warns with what it listens on and what each input delivered, names the topics on the graph
that carry an input with another image transport (image_transport's `<base>/<transport>`: a bag
replayed with compressed colour while `color_transport: raw`), and says whether TF (map_frame <- the
colour image's frame) or CameraInfo is what is missing. /ground's "map is empty" answer says the same.

The report is made by pure functions of plain values (InputState), testable without ROS; the
mixin InputWatch fills an InputState from the node (counters, the ROS graph, the TF buffer).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

from .params import TRANSPORTS, NodeParams

IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
ROLE_NAMES = {"color": "colour", "depth": "depth", "info": "camera_info", "pose": "pose"}
TRANSPORT_PARAMS = {"color": "color_transport", "depth": "depth_transport"}
REPEAT = 30.0   # s between repeated warnings while no frame arrives


@dataclass
class InputState:
    """What the node knows about its inputs, as plain values."""

    topics: dict[str, str]                       # role (color, depth, info, pose) -> the topic it listens on
    counts: dict[str, int]                       # role -> messages received
    transports: dict[str, str] = field(default_factory=lambda: {"color_transport": "raw", "depth_transport": "raw"})
    published: dict[str, list[str]] = field(default_factory=dict)   # topics with a publisher -> their types
    pose_source: str = "tf"
    map_frame: str = "map"
    cam_frame: str | None = None                 # header.frame_id of the latest colour image
    tf_ok: bool | None = None                    # map_frame <- cam_frame can be looked up (None: not checked)
    tf_why: str = ""                             # why not
    tf_frames: int = 0                           # frames the TF buffer knows
    paired: int = 0                              # colour/depth/info sets out of the synchroniser
    frames: int = 0                              # frames that reached the mapper
    errors: dict[str, int] = field(default_factory=dict)   # the node's input_errors


def base_topic(topic: str, transport: str) -> str:
    """The image topic under its transport's sub-topic (`<base>/compressed` -> `<base>`)."""
    suffix = "/" + transport
    return topic[: -len(suffix)] if transport != "raw" and topic.endswith(suffix) else topic


def transport_topic(base: str, transport: str) -> str:
    return base if transport == "raw" else f"{base}/{transport}"


def watched_names(topics: dict[str, str], transports: dict[str, str]) -> set[str]:
    """The topics whose publishers matter: the inputs and their images under every transport the node takes."""
    names = set(topics.values())
    for role, param in TRANSPORT_PARAMS.items():
        if role in topics:
            base = base_topic(topics[role], transports.get(param, "raw"))
            names |= {transport_topic(base, t) for t in TRANSPORTS[param]}
    return names


def expected_type(role: str, s: InputState) -> str:
    if role in TRANSPORT_PARAMS:
        return IMAGE if s.transports.get(TRANSPORT_PARAMS[role], "raw") == "raw" else COMPRESSED
    return {"info": "sensor_msgs/msg/CameraInfo", "pose": "nav_msgs/msg/Odometry" if s.pose_source == "odometry"
            else "geometry_msgs/msg/PoseStamped"}[role]


def transport_hints(role: str, s: InputState) -> list[str]:
    """The image of `role` published under another transport than the node's: what to set."""
    param = TRANSPORT_PARAMS.get(role)
    if param is None or role not in s.topics:
        return []
    current = s.transports.get(param, "raw")
    base = base_topic(s.topics[role], current)
    out = []
    for t in TRANSPORTS[param]:
        name = transport_topic(base, t)
        if t != current and name in s.published:
            out.append(f"{name} is published ({', '.join(s.published[name])}): set {param}: {t}")
    return out


def topic_note(role: str, s: InputState) -> str:
    """Why an input with no message may have none: another transport, another type, no publisher."""
    hints = transport_hints(role, s)
    if hints:
        return f" (but {'; '.join(hints)})"
    topic, want = s.topics[role], expected_type(role, s)
    types = s.published.get(topic)
    if types is None:
        return " (no publisher)"
    if want not in types:
        return f" (published as {', '.join(types)}; the node takes {want})"
    return " (published, nothing received yet)"


def inputs_line(s: InputState) -> str:
    """'received colour 0 on /a (no publisher), depth 12 on /b, ...'"""
    parts = []
    for role, topic in s.topics.items():
        n = s.counts.get(role, 0)
        parts.append(f"{ROLE_NAMES.get(role, role)} {n} on {topic}" + ("" if n else topic_note(role, s)))
    return "received " + ", ".join(parts)


def tf_line(s: InputState) -> str:
    """The state of the transform poses come from (pose_source tf; '' otherwise)."""
    if s.pose_source != "tf":
        return ""
    if s.cam_frame == "":
        return f"TF {s.map_frame} <- '': the colour image has an empty header.frame_id (TF needs its optical frame)"
    if s.cam_frame is None:
        return (f"TF {s.map_frame} <- the colour image's frame: " + (
            f"{s.tf_frames} frames on /tf, /tf_static; which one is known once a colour image arrives"
            if s.tf_frames else "nothing on /tf or /tf_static yet"))
    head = f"TF {s.map_frame} <- {s.cam_frame}: "
    if s.tf_ok:
        return head + "available"
    return head + ("none yet (nothing on /tf or /tf_static)" if not s.tf_frames else s.tf_why or "missing")


def what_is_missing(s: InputState) -> str:
    """The first thing between the topics and the map that is missing ('' when frames reach the map)."""
    if s.frames:
        return ""
    missing = [r for r in s.topics if not s.counts.get(r, 0)]
    if len(missing) == len(s.topics):
        return "nothing received on any input"
    if missing:
        names = [ROLE_NAMES.get(r, r) for r in missing]
        why = "no " + " and no ".join(names) + " received"
        if "info" in missing and ("color" not in missing or "depth" not in missing):
            why += " (frames cannot be mapped without intrinsics)"
        return why
    if not s.paired:
        return "every input arrives but no set was paired: their stamps differ by more than sync_slop"
    if s.pose_source == "tf" and not s.tf_ok:
        return f"frames wait for TF {s.map_frame} <- {s.cam_frame or 'the colour frame'}"
    errs = ", ".join(f"{k} {v}" for k, v in sorted(s.errors.items()))
    return "frames were rejected" + (f" (input errors: {errs}; see the log)" if errs else " (see the log)")


def report(s: InputState, head: str) -> str:
    """`head` (e.g. 'no frame mapped yet'), what is missing, what each input received, TF."""
    why = what_is_missing(s)
    parts = [f"{head} ({why})" if why else head, inputs_line(s)]
    tf = tf_line(s)
    return "; ".join(parts + ([tf] if tf else []))


def empty_map_message(s: InputState) -> str:
    """/ground's answer while the map has no keyframe."""
    head = ("no frame mapped yet" if not s.frames
            else f"{s.frames} frames reached the mapper, none is a keyframe yet")
    return "map is empty: " + report(s, head)


class InputWatch:
    """Mixin of GroundingNode: the input report and the warning when no frame comes. Uses the
    node's parameters (self.p), topics, msgs_in, sync, tf, worker and input_errors."""

    def _make_input_watch(self, p: NodeParams) -> None:
        self._watch_frames = 0
        self._watch_since = time.monotonic()   # the last time a frame reached the mapper (or the start)
        self._watch_warned: float | None = None
        if p.input_timeout > 0:
            self.create_timer(min(1.0, p.input_timeout / 2), self._on_input_watch,
                              callback_group=MutuallyExclusiveCallbackGroup())

    def input_state(self) -> InputState:
        p = self.p
        transports = {"color_transport": p.color_transport, "depth_transport": p.depth_transport}
        topics = {r: self.topics[r] for r in self.msgs_in}   # the sensor inputs (not clicked_point)
        names = watched_names(topics, transports)
        published = {n: list(t) for n, t in self.get_topic_names_and_types() if n in names and self.count_publishers(n)}
        cam = getattr(self, "_color_frame", None)
        ok, why = self.tf.can_transform(p.map_frame, cam) if cam else (None, "")
        return InputState(topics=topics, counts=dict(self.msgs_in), transports=transports,
                          published=published, pose_source=p.pose_source, map_frame=p.map_frame, cam_frame=cam,
                          tf_ok=ok, tf_why=why, tf_frames=len(self.tf.frames), paired=self.sync.emitted,
                          frames=int(self.worker.stats()["received"]), errors=dict(self.input_errors))

    def empty_map_message(self) -> str:
        return empty_map_message(self.input_state())

    def _on_input_watch(self) -> None:
        now = time.monotonic()
        frames = int(self.worker.stats()["received"])
        if frames != self._watch_frames:
            self._watch_frames, self._watch_since, self._watch_warned = frames, now, None
            return
        idle = now - self._watch_since
        if idle < self.p.input_timeout or (self._watch_warned is not None and now - self._watch_warned < REPEAT):
            return
        self._watch_warned = now
        head = f"no frame {'mapped yet' if not frames else 'reached the map'} for {idle:.0f} s"
        self._input_warning(report(self.input_state(), head))

    def _input_warning(self, msg: str) -> None:
        """Logged, not counted in input_errors (those count bad messages; this is their absence)."""
        self.get_logger().warning(msg)
