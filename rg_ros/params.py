"""rg_node's parameters and names: one place for the defaults, descriptions, ranges and choices
(`ros2 param describe`), the relative names the node uses and the launch file's default remappings."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from rg_core.io.rosbag import POSE_SOURCES

NODE_NAME = "rg_node"


def _p(default, doc: str, lo: float | None = None, hi: float | None = None, choices: tuple[str, ...] = ()):
    """A node parameter: default (its type is the parameter's type), description, inclusive range or choices."""
    return field(default=default, metadata={"doc": doc, "range": None if lo is None else (lo, hi),
                                            "choices": choices})


# Relative names the node subscribes and serves (set by remapping, as image_pipeline's nodes do) and
# the camera topics the launch file remaps them to by default (a realsense2_camera-style driver in
# namespace /camera). rg-replay publishes on these defaults.
INPUTS = {"rgb/image": "/camera/color/image_raw", "depth/image": "/camera/aligned_depth_to_color/image_raw",
          "rgb/camera_info": "/camera/color/camera_info", "pose": "/camera/pose", "odom": "/odom"}
GROUND_SERVICE = "ground"
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
    pose_source: str = _p("tf", "tf: look up map_frame <- the colour image's header.frame_id on /tf and "
                          "/tf_static at its stamp; topic: geometry_msgs/PoseStamped on 'pose'; odometry: "
                          "nav_msgs/Odometry on 'odom', chained with TF to the image's frame",
                          choices=POSE_SOURCES)
    map_frame: str = _p("map", "frame of poses, clouds and markers")
    tf_wait: float = _p(0.5, "seconds a frame waits for its transform; then it is dropped and counted "
                        "(diagnostics 'tf')", 0.0, 60.0)
    tf_cache_time: float = _p(10.0, "seconds of dynamic TF history kept", 0.1, 3600.0)
    tf_max_gap: float = _p(0.5, "a dynamic TF link is not interpolated across a longer gap between samples "
                           "(s); 0 = any gap, as tf2", 0.0, 3600.0)
    tf_extrapolation: float = _p(0.0, "seconds past a link's newest (or before its oldest) sample where its "
                                 "nearest sample is used (tf2: 0)", 0.0, 60.0)
    sync_queue_size: int = _p(10, "messages per input kept by the approximate time synchroniser", 1, 1000)
    sync_slop: float = _p(0.05, "largest stamp spread (s) of one synchronised colour/depth/info set", 0.0, 10.0)
    frame_queue_size: int = _p(4, "frames waiting for the mapper; when full the oldest is dropped and counted",
                               1, 100000)
    rg_config: str = _p("", "rg YAML configuration (map and field sections); empty = defaults")
    map_width: int = _p(0, "mapper working width in pixels (0 = rg_config's map.width)", 0, 8192)
    iters_per_keyframe: int = _p(0, "optimisation iterations per keyframe (0 = rg_config's)", 0, 100000)
    max_gaussians: int = _p(0, "bound on the map's Gaussians (0 = rg_config's)", 0, 1_000_000_000)
    load_map: str = _p("", "map file loaded at start-up (empty = start with an empty map)")
    save_path: str = _p("rg_map.pt", "where ~/save_map (and the save on shutdown) writes the map")
    save_on_shutdown: bool = _p(False, "save the map to save_path when the node stops (SIGINT, SIGTERM)")
    features: bool = _p(True, "keyframe supervision and feature-field training while the mapper is idle")
    mask_generator: str = _p("rgbd", "mask generator backend of the supervision")
    embedder: str = _p("conse", "image-text embedder backend of the supervision")
    preset: str = _p("", "named models (rg models): offline, paper, paper_cpu; overrides mask_generator, "
                     "embedder and the reasoner (empty = those parameters)")
    train_slice: float = _p(0.5, "seconds of field training per idle slice", 0.01, 600.0)
    train_seconds_max: float = _p(30.0, "field training seconds after each supervision change (0 = whenever "
                                  "idle)", 0.0, 1e6)
    refine_iters: int = _p(0, "map refinement iterations per idle slice (0 = off)", 0, 100000)
    torch_threads: int = _p(0, "torch intra-op threads (0 = torch's default)", 0, 1024)
    max_results: int = _p(1, "objects returned when a request says max_results = 0", 1, 1000)
    max_query_chars: int = _p(1000, "longer queries are refused", 1, 1_000_000)
    ground_timeout: float = _p(30.0, "seconds a grounding call waits for the map lock", 0.1, 3600.0)
    mask_rate: float = _p(2.0, "Hz of ~/amodal_mask and ~/visible_mask for the last grounded targets (0 = off)",
                          0.0, 100.0)
    map_cloud_period: float = _p(5.0, "seconds between ~/map_cloud messages, sent only while someone "
                                 "subscribes (0 = off)", 0.0, 3600.0)
    map_cloud_max_points: int = _p(50000, "Gaussians per ~/map_cloud message (evenly subsampled)", 1, 100_000_000)
    status_period: float = _p(1.0, "seconds between /diagnostics messages", 0.05, 3600.0)
    camera_info_timeout: float = _p(5.0, "warn when images arrive but no CameraInfo came for this long (s)",
                                    0.0, 3600.0)
    marker_alpha: float = _p(0.25, "opacity of the grounded boxes (CUBE markers)", 0.0, 1.0)


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
