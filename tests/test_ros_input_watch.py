"""Inputs that never arrive are reported (rg_ros/input_watch.py, issue 62): the pure report from plain
values (which transport to set, TF or CameraInfo missing, nothing at all), and one node in this
process whose colour is published compressed while it listens raw: /ground's "map is empty" and the
warning name the compressed topic. Every ROS step waits on a condition (the graph seeing the
publisher, a warning recorded), never on time or on how many messages were delivered.
"""
from __future__ import annotations

import os
import random
import sys
import threading
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # never multicast onto the network
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("ROS_LOG_DIR", str(Path(__file__).resolve().parents[1] / ".ros_log"))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest  # noqa: E402

rclpy = pytest.importorskip("rclpy")
from rg_ros.input_watch import (COMPRESSED, IMAGE, InputState, empty_map_message, inputs_line, report,  # noqa: E402
                                tf_line, watched_names, what_is_missing)

CAM = "/camera/color/image_raw"
DEPTH = "/camera/aligned_depth_to_color/image_raw"
INFO = "/camera/color/camera_info"
OPTICAL = "camera_color_optical_frame"


def state(counts=(0, 0, 0), published=None, **kw) -> InputState:
    """The launch file's default topics, raw transports, pose from TF."""
    topics = kw.pop("topics", {"color": CAM, "depth": DEPTH, "info": INFO})
    return InputState(topics=topics, counts=dict(zip(topics, counts)), published=published or {}, **kw)


# ------------------------------------------------------------------------------ the pure report

def test_the_users_case_names_the_compressed_colour_topic():
    """A bag replayed with compressed colour, the node on raw: depth and CameraInfo arrive, colour never."""
    s = state((0, 120, 120), {f"{CAM}/compressed": [COMPRESSED], DEPTH: [IMAGE], INFO: ["sensor_msgs/msg/CameraInfo"],
                              f"{DEPTH}/compressedDepth": [COMPRESSED]}, cam_frame=None, tf_frames=4)
    msg = empty_map_message(s)
    assert msg == (f"map is empty: no frame mapped yet (no colour received); received colour 0 on {CAM} (but "
                   f"{CAM}/compressed is published ({COMPRESSED}): set color_transport: compressed), depth 120 on "
                   f"{DEPTH}, camera_info 120 on {INFO}; TF map <- the colour image's frame: 4 frames on /tf, "
                   "/tf_static; which one is known once a colour image arrives"), msg


@pytest.mark.parametrize("transports, published, want", [
    ({"color_transport": "raw", "depth_transport": "raw"}, {f"{DEPTH}/compressedDepth": [COMPRESSED]},
     f"depth 0 on {DEPTH} (but {DEPTH}/compressedDepth is published ({COMPRESSED}): "
     "set depth_transport: compressedDepth)"),
    ({"color_transport": "compressed", "depth_transport": "raw"}, {CAM: [IMAGE]},
     f"colour 0 on {CAM}/compressed (but {CAM} is published ({IMAGE}): set color_transport: raw)"),
    ({"color_transport": "raw", "depth_transport": "compressedDepth"}, {DEPTH: [IMAGE]},
     f"depth 0 on {DEPTH}/compressedDepth (but {DEPTH} is published ({IMAGE}): set depth_transport: raw)"),
])
def test_another_transport_on_the_graph_is_named(transports, published, want):
    topics = {"color": CAM if transports["color_transport"] == "raw" else f"{CAM}/compressed",
              "depth": DEPTH if transports["depth_transport"] == "raw" else f"{DEPTH}/compressedDepth", "info": INFO}
    line = inputs_line(state(published=published, topics=topics, transports=transports))
    assert want in line, line


def test_no_transport_the_node_cannot_take_and_no_type_it_does_not_take():
    """Depth on <base>/compressed and colour on <base>/theora are not suggested (the node decodes neither);
    a listened topic published with another type says so."""
    s = state(published={f"{DEPTH}/compressed": [COMPRESSED], f"{CAM}/theora": ["theora_image_transport/msg/Packet"],
                         INFO: [COMPRESSED]})
    line = inputs_line(s)
    assert "set " not in line, line
    assert f"colour 0 on {CAM} (no publisher)" in line and f"depth 0 on {DEPTH} (no publisher)" in line, line
    assert f"camera_info 0 on {INFO} (published as {COMPRESSED}; the node takes sensor_msgs/msg/CameraInfo)" in line
    assert "(published, nothing received yet)" in inputs_line(state(published={CAM: [IMAGE]}))
    assert watched_names(s.topics, s.transports) == {CAM, f"{CAM}/compressed", DEPTH, f"{DEPTH}/compressedDepth", INFO}


def test_nothing_arrived_at_all():
    msg = empty_map_message(state())
    assert msg == (f"map is empty: no frame mapped yet (nothing received on any input); received colour 0 on {CAM} "
                   f"(no publisher), depth 0 on {DEPTH} (no publisher), camera_info 0 on {INFO} (no publisher); "
                   "TF map <- the colour image's frame: nothing on /tf or /tf_static yet"), msg


def test_camera_info_missing_while_images_arrive():
    s = state((30, 30, 0), cam_frame=OPTICAL, tf_ok=True, tf_frames=5)
    assert what_is_missing(s) == "no camera_info received (frames cannot be mapped without intrinsics)"
    assert tf_line(s) == f"TF map <- {OPTICAL}: available"


@pytest.mark.parametrize("tf_frames, why, want", [
    (0, "", f"TF map <- {OPTICAL}: none yet (nothing on /tf or /tf_static)"),
    (2, f'"{OPTICAL}" passed to lookup (source frame) does not exist; known frames: base, odom',
     f'TF map <- {OPTICAL}: "{OPTICAL}" passed to lookup (source frame) does not exist; known frames: base, odom'),
])
def test_tf_missing_when_every_input_arrives(tf_frames, why, want):
    s = state((30, 30, 30), cam_frame=OPTICAL, tf_ok=False, tf_why=why, tf_frames=tf_frames, paired=30)
    assert what_is_missing(s) == f"frames wait for TF map <- {OPTICAL}"
    assert report(s, "no frame mapped yet").endswith("; " + want), report(s, "no frame mapped yet")
    assert "empty header.frame_id" in tf_line(state(cam_frame=""))


def test_what_is_missing_after_the_inputs():
    """Unpaired stamps, rejected frames, frames mapped; a PoseStamped source has no TF line."""
    arrived = dict(cam_frame=OPTICAL, tf_ok=True, tf_frames=5)
    assert "no set was paired" in what_is_missing(state((9, 9, 9), **arrived))
    assert what_is_missing(state((9, 9, 9), paired=9, errors={"size": 9}, **arrived)) == (
        "frames were rejected (input errors: size 9; see the log)")
    assert empty_map_message(state((9, 9, 9), paired=9, frames=3, **arrived)).startswith(
        f"map is empty: 3 frames reached the mapper, none is a keyframe yet; received colour 9 on {CAM}")
    s = state((5, 5, 5, 0), topics={"color": CAM, "depth": DEPTH, "info": INFO, "pose": "/camera/pose"},
              pose_source="topic")
    assert tf_line(s) == "" and what_is_missing(s) == "no pose received"
    assert report(s, "h").endswith("camera_info 5 on /camera/color/camera_info, pose 0 on /camera/pose (no publisher)")


# ------------------------------------------------------------------------------ one node in this process

@pytest.fixture(scope="module")
def watched():
    """rg_node (features off) on topics of its own, input_timeout 1 s, its warnings recorded; a probe
    node publishing compressed colour where the node listens raw."""
    pytest.importorskip("rg_interfaces.srv", reason="rg_interfaces is not installed: scripts/bootstrap.sh builds it")
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CompressedImage

    from rg_ros.node import GroundingNode
    from rg_ros.run import NodeExecutor

    prefix = f"/watch{os.getpid()}"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    remap = {"rgb/image": f"{prefix}/color/image_raw", "depth/image": f"{prefix}/depth/image_raw",
             "rgb/camera_info": f"{prefix}/color/camera_info", "ground": f"{prefix}/ground"}   # no other node's
    params = dict(features=False, input_timeout=1.0, status_period=3600.0, mask_rate=0.0, map_cloud_period=0.0,
                  scene_graph_period=0.0, torch_threads=1, gil_switch_interval=0.002)
    switch = sys.getswitchinterval()   # process-wide: given back after the module
    args = ["--ros-args", *[a for k, v in remap.items() for a in ("-r", f"{k}:={v}")]]
    node = GroundingNode(context=ctx, cli_args=args,
                         parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    warnings: list[str] = []
    node._input_warning = warnings.append   # before the first spin
    probe = rclpy.create_node("rg_watch_probe", context=ctx)
    compressed = f"{prefix}/color/image_raw/compressed"
    probe.create_publisher(CompressedImage, compressed, qos_profile_sensor_data)
    executor = NodeExecutor(context=ctx)
    executor.add_node(node)
    executor.add_node(probe)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield dict(node=node, probe=probe, prefix=prefix, compressed=compressed, warnings=warnings)
    finally:
        node.shutdown()
        executor.shutdown(timeout_sec=5)
        node.destroy_node()
        probe.destroy_node()
        ctx.try_shutdown()
        thread.join(timeout=5)
        sys.setswitchinterval(switch)


def wait_for(cond, timeout: float, what: str):
    from test_ros_node import wait_for as wait   # imported here: it needs rg_interfaces, the pure tests do not

    return wait(cond, timeout, what)


def test_ground_names_the_compressed_colour_topic(watched):
    from rg_interfaces.srv import Ground

    node, compressed = watched["node"], watched["compressed"]
    wait_for(lambda: node.count_publishers(compressed) > 0, 60, f"the node's graph to see {compressed}")
    client = watched["probe"].create_client(Ground, f"{watched['prefix']}/ground")
    try:
        assert client.wait_for_service(timeout_sec=60), "the node's ground service not discovered"
        res = client.call(Ground.Request(query="the mug"), timeout_sec=60)
    finally:
        watched["probe"].destroy_client(client)
    assert res is not None and not res.success
    assert res.message.startswith("map is empty: no frame mapped yet (nothing received on any input)"), res.message
    assert (f"colour 0 on {watched['prefix']}/color/image_raw (but {compressed} is published "
            f"(sensor_msgs/msg/CompressedImage): set color_transport: compressed)") in res.message, res.message
    assert f"depth 0 on {watched['prefix']}/depth/image_raw (no publisher)" in res.message, res.message


def test_node_sets_the_gil_switch_interval(watched):
    """gil_switch_interval is applied to the process (a query's torch calls get the GIL back
    within it beside the mapping thread and the executor; bench_endurance --busy measures that)."""
    assert sys.getswitchinterval() == pytest.approx(0.002)


def test_warns_when_no_frame_comes(watched):
    """No frame ever comes: the timer warns (input_timeout 1 s) with the topics and their counts."""
    msg = wait_for(lambda: next(iter(watched["warnings"]), None), 60, "the no-frame warning")
    assert msg.startswith("no frame mapped yet for "), msg
    assert f"received colour 0 on {watched['prefix']}/color/image_raw" in msg, msg
