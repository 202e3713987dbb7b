"""rg_node's parameters and names: one place for the defaults, descriptions, ranges and choices
(`ros2 param describe`), the relative names the node uses and the launch file's default remappings."""
from __future__ import annotations

import dataclasses
import functools
import typing
from dataclasses import dataclass, field
from typing import Annotated

from annotated_types import Interval
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos_overriding_options import QoSOverridingOptions

from rg_core.config import GroundConfig, check_fields, section
from rg_core.io.ros_input import InputConfig

# qos_overrides./<topic>.<publisher|subscription>.{history,depth,reliability} parameters for every
# topic the node subscribes or publishes
QOS_OVERRIDES = QoSOverridingOptions.with_default_policies()

NODE_NAME = "rg_node"


@section
class WorkerConfig:
    """What the map worker does besides mapping (the node's parameters of the same names)."""

    queue_size: Annotated[int, Interval(ge=1, le=100000)] = 4
    """Frames waiting for the mapper; when full the oldest is dropped and counted."""
    features: bool = True
    """Keyframe supervision and feature-field training while the mapper is idle."""
    mask_generator: str = "rgbd"
    """Mask generator backend of the supervision (rg_core.perception.masks)."""
    embedder: str = "conse"
    """Image-text embedder backend of the supervision and queries (rg_core.perception.embed)."""
    train_slice: Annotated[float, Interval(ge=0.01, le=600.0)] = 0.5
    """Seconds of field training per idle slice (the map lock is held for one slice; a service call
    waiting for it ends the slice after its current step)."""
    train_seconds_max: Annotated[float, Interval(ge=0.0, le=1e6)] = 30.0
    """Field training seconds after each supervision change (0 = whenever idle)."""
    refine_iters: Annotated[int, Interval(ge=0, le=100000)] = 0
    """Map refinement iterations per idle slice (0 = off): slices of one refinement that stops as
    `rg map`'s does (map.refine_tol), at most map.final_iters per keyframe."""
    idle_wait: Annotated[float, Interval(gt=0.0, le=60.0)] = 0.2
    """Seconds the worker sleeps waiting for a frame when it has nothing else to do."""
    slow_query: Annotated[float, Interval(gt=0.0)] = 0.5
    """A /ground answer slower than this (s) is logged with where its time went."""
    mapping_nice: Annotated[int, Interval(ge=0, le=19)] = 10
    """Niceness of the mapping thread (Linux, per thread): queries and callbacks get the CPU first."""
    yield_to_queries: Annotated[float, Interval(ge=0.0, le=60.0)] = 2.0
    """Seconds at most the mapping thread waits before its next unit of work while a /ground or
    point query runs (queries never wait for mapping; this gives them the CPU; 0 = never wait)."""

    def __post_init__(self):
        check_fields(self)


def _p(default, doc: str, lo: float | None = None, hi: float | None = None, choices: tuple[str, ...] = ()):
    """A node parameter: default (its type is the parameter's type), description, inclusive range or choices."""
    return field(default=default, metadata={"doc": doc, "range": None if lo is None else (lo, hi),
                                            "choices": choices})


@functools.cache
def _docs(cls: type) -> dict[str, str]:
    from pydantic import TypeAdapter   # the attribute docstrings, as pydantic reads them
    return {k: v.get("description", "") for k, v in TypeAdapter(cls).json_schema()["properties"].items()}


def _from(cls: type, name: str):
    """A node parameter defined by a config section's field: its default, docstring, range and choices."""
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    tp = typing.get_type_hints(cls, include_extras=True)[name]
    rng = next((m for m in getattr(tp, "__metadata__", ()) if isinstance(m, Interval)), None)
    lo = None if rng is None else (rng.ge if rng.ge is not None else rng.gt)
    hi = None if rng is None else (rng.le if rng.le is not None else rng.lt)
    choices = typing.get_args(tp) if typing.get_origin(tp) is typing.Literal else ()
    return _p(f.default, _docs(cls)[name], lo, hi, choices)


# Relative names the node subscribes and serves (set by remapping, as image_pipeline's nodes do) and
# the camera topics the launch file remaps them to by default (a realsense2_camera-style driver in
# namespace /camera). rg-replay publishes on these defaults.
INPUTS = {"rgb/image": "/camera/color/image_raw", "depth/image": "/camera/aligned_depth_to_color/image_raw",
          "rgb/camera_info": "/camera/color/camera_info", "pose": "/camera/pose", "odom": "/odom"}
GROUND_SERVICE = "ground"
CLICKED_POINT_TOPIC = "clicked_point"   # RViz's Publish Point tool publishes /clicked_point (a PointStamped)
DIAGNOSTICS_TOPIC = "/diagnostics"   # diagnostic_updater's absolute name (remappable like any other)
TRANSPORTS = {"color_transport": ("raw", "compressed"), "depth_transport": ("raw", "compressedDepth")}


@dataclass
class NodeParams:
    """The node's ROS parameters, the one place they are declared from: name, default (the type
    follows it), description and range (shown by `ros2 param describe`). All are read once at
    start-up, so all are read-only."""

    color_transport: str = _p("raw", "image_transport of rgb/image: raw (sensor_msgs/Image rgb8, bgr8, rgba8, "
                              "bgra8, mono8) or compressed (CompressedImage jpeg/png on rgb/image/compressed)",
                              choices=TRANSPORTS["color_transport"])
    depth_transport: str = _p("raw", "image_transport of depth/image (registered to the colour image): raw "
                              "(16UC1 mm or 32FC1 m) or compressedDepth (on depth/image/compressedDepth)",
                              choices=TRANSPORTS["depth_transport"])
    pose_source: str = _from(InputConfig, "pose_source")
    map_frame: str = _from(InputConfig, "map_frame")
    tf_wait: float = _from(InputConfig, "tf_wait")
    tf_cache_time: float = _from(InputConfig, "tf_cache_time")
    tf_max_gap: float = _from(InputConfig, "tf_max_gap")
    tf_extrapolation: float = _from(InputConfig, "tf_extrapolation")
    sync_queue_size: int = _from(InputConfig, "sync_queue_size")
    sync_slop: float = _from(InputConfig, "sync_slop")
    frame_queue_size: int = _from(WorkerConfig, "queue_size")
    rg_config: str = _p("", "rg YAML configuration (map and field sections); empty = defaults")
    map_width: int = _p(0, "mapper working width in pixels (0 = rg_config's map.width)", 0, 8192)
    iters_per_keyframe: int = _p(0, "optimisation iterations per keyframe (0 = rg_config's)", 0, 100000)
    max_gaussians: int = _p(0, "bound on the map's Gaussians (0 = rg_config's)", 0, 1_000_000_000)
    max_keyframes: int = _p(0, "bound on the map's keyframes and their supervision (0 = rg_config's)", 0, 1_000_000)
    load_map: str = _p("", "map file loaded at start-up (empty = start with an empty map)")
    save_path: str = _p("rg_map.pt", "where ~/save_map (and the save on shutdown) writes the map")
    save_on_shutdown: bool = _p(False, "save the map to save_path when the node stops (SIGINT, SIGTERM)")
    features: bool = _from(WorkerConfig, "features")
    mask_generator: str = _from(WorkerConfig, "mask_generator")
    embedder: str = _from(WorkerConfig, "embedder")
    preset: str = _p("", "named models (rg models): offline, paper, paper_cpu; overrides mask_generator, "
                     "embedder and the reasoner (empty = those parameters)")
    train_slice: float = _from(WorkerConfig, "train_slice")
    train_seconds_max: float = _from(WorkerConfig, "train_seconds_max")
    refine_iters: int = _from(WorkerConfig, "refine_iters")
    torch_threads: int = _p(0, "torch intra-op threads (0 = torch's default)", 0, 1024)
    gil_switch_interval: float = _p(0.0005, "s a thread holding Python's GIL keeps it while another waits "
                                    "(sys.setswitchinterval; 0 = Python's 0.005): short, so a query's torch "
                                    "calls get the GIL back quickly beside mapping and the executor", 0.0, 0.1)
    max_results: int = _p(1, "objects returned when a request says max_results = 0", 1, 1000)
    max_query_chars: int = _from(GroundConfig, "max_query_chars")
    min_confidence: float = _from(GroundConfig, "min_confidence")
    ground_timeout: float = _p(30.0, "seconds a grounding call waits for the map lock", 0.1, 3600.0)
    mask_rate: float = _p(2.0, "Hz of ~/amodal_mask and ~/visible_mask for the last grounded targets (0 = off)",
                          0.0, 100.0)
    map_cloud_period: float = _p(5.0, "seconds between ~/map_cloud messages, sent only while someone "
                                 "subscribes (0 = off)", 0.0, 3600.0)
    map_cloud_max_points: int = _p(50000, "Gaussians per ~/map_cloud message (evenly subsampled)", 1, 100_000_000)
    status_period: float = _p(1.0, "seconds between /diagnostics messages", 0.05, 3600.0)
    camera_info_timeout: float = _p(5.0, "warn when images arrive but no CameraInfo came for this long (s)",
                                    0.0, 3600.0)
    input_timeout: float = _p(5.0, "warn when no frame reached the map for this long (s), with what each input "
                              "received, topics published with another transport and whether TF or CameraInfo "
                              "is missing (0 = off)", 0.0, 3600.0)
    marker_alpha: float = _p(0.25, "opacity of the grounded boxes (CUBE markers)", 0.0, 1.0)
    scene_graph_period: float = _p(30.0, "seconds between ~/scene_graph updates (latched, with text markers on "
                                   "~/scene_graph_markers; rebuilt only when the map changed; 0 = after /ground "
                                   "answers only)", 0.0, 86400.0)

    def input_config(self) -> InputConfig:
        return InputConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(InputConfig)})

    def worker_config(self) -> WorkerConfig:
        names = {f.name for f in dataclasses.fields(WorkerConfig)} - {"queue_size", "idle_wait", "yield_to_queries", "mapping_nice", "slow_query"}
        return WorkerConfig(queue_size=self.frame_queue_size, **{n: getattr(self, n) for n in names})


PARAM_FIELDS = {f.name: f for f in dataclasses.fields(NodeParams)}
PARAM_NAMES = tuple(PARAM_FIELDS)


def descriptor(name: str) -> ParameterDescriptor:
    """The ParameterDescriptor of a NodeParams field (description, range or choices, read-only)."""
    f = PARAM_FIELDS[name]
    d = ParameterDescriptor(name=name, description=f.metadata["doc"], read_only=True)
    rng, choices = f.metadata["range"], f.metadata["choices"]
    if rng is not None and isinstance(f.default, float):
        d.floating_point_range = [FloatingPointRange(from_value=float(rng[0]), to_value=float(rng[1]), step=0.0)]
    elif rng is not None:
        d.integer_range = [IntegerRange(from_value=int(rng[0]), to_value=int(rng[1]), step=1)]
    if choices:
        d.additional_constraints = "one of: " + ", ".join(choices)
    return d


def declare_params(node: Node) -> NodeParams:
    """Declare every NodeParams field on `node` with its descriptor; return the values. A name
    NodeParams does not declare, a wrong type, a value out of range or not among the choices is a
    ValueError naming the parameter."""
    # rclpy keeps the node's overrides (params files, -p, parameter_overrides) in _parameter_overrides.
    # YAML `1` for a float parameter is an int there; rcl would refuse it as the wrong type.
    overrides = node._parameter_overrides
    for name, prm in list(overrides.items()):
        f = PARAM_FIELDS.get(name)
        if f is not None and isinstance(f.default, float) and prm.type_ == Parameter.Type.INTEGER:
            overrides[name] = Parameter(name, value=float(prm.value))
    check_unknown_params(node, qos_only=False)
    values = {}
    for name, f in PARAM_FIELDS.items():
        try:
            values[name] = node.declare_parameter(name, f.default, descriptor(name)).value
        except InvalidParameterTypeException as exc:
            got = overrides[name].value if name in overrides else None
            raise ValueError(f"parameter '{name}' must be {type(f.default).__name__}, got {got!r}") from exc
        except InvalidParameterValueException as exc:
            raise ValueError(f"parameter '{name}': {exc}") from exc
        choices = f.metadata["choices"]
        if choices and values[name] not in choices:
            raise ValueError(f"parameter '{name}': '{values[name]}' is not one of {', '.join(choices)}")
    return NodeParams(**values)


def check_unknown_params(node: Node, qos_only: bool) -> None:
    """An override naming no parameter of this node is an error (rclpy would ignore it silently)."""
    def ours(n):
        return n.startswith("qos_overrides.") if qos_only else not n.startswith("qos_overrides.")

    unknown = sorted(n for n in node._parameter_overrides if ours(n) and n not in PARAM_FIELDS
                     and not node.has_parameter(n))
    if unknown:
        known = (sorted("qos_overrides." + n for n in node.get_parameters_by_prefix("qos_overrides"))
                 if qos_only else list(PARAM_NAMES))
        raise ValueError(f"unknown parameter '{unknown[0]}'" + (f" (and {len(unknown) - 1} more)" if len(unknown) > 1
                         else "") + f"; known: {', '.join(known)}")
