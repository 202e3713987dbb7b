"""Point and teach through the node (rg_ros/teaching.py): RViz's /clicked_point, ~/teach and
~/forget, called the way a person does (`ros2 topic pub --once /clicked_point ...`, `ros2 service
call /rg_node/teach ...`), every bad input refused with the node alive and the map unchanged, and a
taught name surviving ~/save_map and a restart. One node (module fixture) on a small synthetic
scene replayed into it; points from the scene's ground truth (rg_core/eval/teaching.py). Each step
waits on a condition, never on time.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from ros2_cli_util import ROS2
from ros2_cli_util import ros2 as run_ros2
from test_ros_node import Harness as NodeHarness
from test_ros_node import TOPICS_A, ros_args, start, status_values, stop, wait_for, write_params

pytest.importorskip("rg_interfaces.srv", reason="rg_interfaces is not installed: scripts/bootstrap.sh builds it from msg/")
pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs is not installed: scripts/bootstrap.sh builds it from msg_tf2/")
try:
    from rg_interfaces.srv import Forget, Ground, MapFile, Teach
except ImportError:   # pragma: no cover - an rg_interfaces built before Teach.srv
    pytest.skip("rg_interfaces predates Teach.srv and Forget.srv: rerun scripts/bootstrap.sh", allow_module_level=True)

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PointStamped, TransformStamped  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rg_interfaces.msg import SceneGraph  # noqa: E402
from sensor_msgs.msg import Image, PointCloud2  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from rg_ros.pointcloud import from_pointcloud2  # noqa: E402
from rg_ros.run import NodeExecutor  # noqa: E402

need_ros2 = pytest.mark.skipif(ROS2 is None, reason="no `ros2` command: a full ROS 2 install, or scripts/bootstrap.sh "
                               "with ../shared/vendor/ros2cli")
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
TABLE = np.array([1.0, 2.0, 0.0])   # map <- table: a static transform the probe publishes


def ros2(*args: str, timeout: float = 120.0) -> str:
    """One literal `ros2` command that must succeed; its stdout + stderr."""
    r = run_ros2(*args, timeout=timeout)
    assert r.returncode == 0, f"`ros2 {' '.join(args)}` exited {r.returncode}: {r.stdout[-2000:]} {r.stderr[-2000:]}"
    return r.stdout + r.stderr


def yaml_point(p) -> str:
    return "{x: %r, y: %r, z: %r}" % tuple(float(v) for v in p)


def cloud_points(cloud) -> set:
    return {tuple(v) for v in np.round(from_pointcloud2(cloud)[0].astype(np.float64), 5)}


def overlap(a: set, b: set) -> float:
    return len(a & b) / max(min(len(a), len(b)), 1)


class Harness(NodeHarness):
    """The node under test, the scene, and this process's rclpy probe (test_ros_node's harness
    with teaching's clients and subscriptions; its log, status and shutdown are shared)."""

    def __init__(self, tmp: Path):
        self.tmp, self.log_a, self.saved = tmp, tmp / "node.log", tmp / "taught.rgmap"
        params = write_params(tmp / "a.yaml", "rg_node", pose_source="topic", map_width=80, iters_per_keyframe=2,
                              torch_threads=1, frame_queue_size=32, features=True, train_slice=0.5,
                              train_seconds_max=2.0, status_period=0.3, save_path=str(self.saved),
                              mask_rate=0.0,   # masks only with a new answer: each one is counted here
                              map_cloud_period=0.0, min_confidence=0.0, scene_graph_period=0.0)
        self.node_a = start(["node", "--params", str(params), *ros_args(TOPICS_A)], self.log_a)
        self.scene = tmp / "scene"   # made while the node starts
        subprocess.run([sys.executable, "-m", "rg_core.cli", "synth", str(self.scene), "--views", "12", "--size",
                        "160x120", "--seed", "3", "--objects", "4", "--json", "--quiet"], env=dict(os.environ),
                       check=True, capture_output=True, timeout=120)
        from rg_core.eval.teaching import simulated_clicks
        from rg_core.io.captures import read_scene

        scene = read_scene(self.scene)
        self.boxes = {o.name: (np.asarray(o.aabb_min), np.asarray(o.aabb_max)) for o in scene.objects}
        self.clicks = {c.name: c.point for c in simulated_clicks(scene)}
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = n = rclpy.create_node("rg_teach_probe", context=self.ctx)
        self.status: dict[str, dict] = {}
        self.got: dict[str, list] = {"cloud": [], "amodal": [], "graph": []}
        n.create_subscription(DiagnosticArray, "/diagnostics", lambda m: self.status.update(status_values(m)), 10)
        n.create_subscription(PointCloud2, "/rg_node/grounded_cloud", lambda m: self.got["cloud"].append(m), LATCHED)
        n.create_subscription(Image, "/rg_node/amodal_mask", lambda m: self.got["amodal"].append(m), 10)
        n.create_subscription(SceneGraph, "/rg_node/scene_graph", lambda m: self.got["graph"].append(m), LATCHED)
        self.teach = n.create_client(Teach, "/rg_node/teach")
        self.forget = n.create_client(Forget, "/rg_node/forget")
        self.ground = n.create_client(Ground, "/ground")
        self.save = n.create_client(MapFile, "/rg_node/save_map")
        self.clicked = n.create_publisher(PointStamped, "/clicked_point", 10)
        tf = n.create_publisher(TFMessage, "/tf_static", LATCHED)
        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = "map", "table"
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (float(v) for v in TABLE)
        t.transform.rotation.w = 1.0
        tf.publish(TFMessage(transforms=[t]))
        self.executor = NodeExecutor(context=self.ctx)
        self.executor.add_node(n)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_for(lambda: self.st() or self.node_a.poll() is not None, 120, "the node's first status")
        assert self.node_a.poll() is None, f"rg-node exited {self.node_a.returncode}:\n{self.log()[-3000:]}"

    def fresh_status(self, name: str = "/rg_node") -> dict:
        t = time.monotonic()
        return wait_for(lambda: self.st(name) if self.st(name).get("_t", 0) > t else None, 20, f"a status of {name}")

    def call(self, client, req, timeout: float = 120.0):
        assert client.wait_for_service(timeout_sec=30), f"{client.srv_name} not discovered"
        res = client.call(req, timeout_sec=timeout)
        assert res is not None, f"{client.srv_name}: no reply within {timeout} s"
        return res

    def teach_at(self, name: str, p, frame: str = "map"):
        req = Teach.Request(name=name)
        req.point.header.frame_id = frame
        req.point.point.x, req.point.point.y, req.point.point.z = (float(v) for v in p)
        return self.call(self.teach, req)



@pytest.fixture(scope="module")
def h(tmp_path_factory):
    harness = Harness(tmp_path_factory.mktemp("rgteach"))
    try:
        yield harness
    finally:
        harness.close()


@pytest.fixture(scope="module")
def mapped(h):
    """The scene replayed into the node; the map once its field has stopped training."""
    rep = subprocess.run([sys.executable, "-m", "rg_ros.tools", "replay", str(h.scene), "--rate", "4"],
                         env=dict(os.environ), capture_output=True, text=True, timeout=120)
    assert rep.returncode == 0, rep.stdout + rep.stderr
    wait_for(lambda: h.st().get("keyframes", 0) > 0 and h.st()["queue"] == 0 and h.st().get("field_stop")
             or h.node_a.poll() is not None, 300, lambda: f"keyframes and a trained field (status {h.st()})")
    assert h.node_a.poll() is None, h.log()[-3000:]
    return h


def test_rviz_publish_point_tool_reaches_the_node():
    """config/grounding.rviz's Publish Point tool publishes where the node listens by default."""
    import yaml

    from rg_ros.params import CLICKED_POINT_TOPIC

    cfg = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "grounding.rviz").read_text())
    tools = [t for t in cfg["Visualization Manager"]["Tools"] if t["Class"] == "rviz_default_plugins/PublishPoint"]
    assert tools and tools[0]["Topic"]["Value"] == "/" + CLICKED_POINT_TOPIC


def test_points_are_transformed_into_the_map_frame():
    """Teaching._to_map with the node's TF buffer: at the point's stamp (interpolated), the latest
    transform for a click stamped after it, and the reason when no transform can be found."""
    from types import SimpleNamespace

    from rg_core.geometry.tf_buffer import TFBuffer
    from rg_ros import convert as cv
    from rg_ros.teaching import FrameProblem, Teaching

    tf = TFBuffer()
    for t, x in ((1.0, 0.0), (2.0, 1.0)):
        tf.set_transform("map", "odom", t, [x, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    node = SimpleNamespace(tf=tf, p=SimpleNamespace(map_frame="map"))

    def point(frame, stamp, xyz=(0.0, 0.5, 0.25)):
        m = PointStamped()
        m.header.frame_id, m.header.stamp = frame, cv.to_time(stamp)
        m.point.x, m.point.y, m.point.z = xyz
        return m

    np.testing.assert_allclose(Teaching._to_map(node, point("odom", 1.5)), [0.5, 0.5, 0.25])
    np.testing.assert_allclose(Teaching._to_map(node, point("odom", 9.0)), [1.0, 0.5, 0.25])   # the latest
    np.testing.assert_allclose(Teaching._to_map(node, point("/map", 0.0)), [0.0, 0.5, 0.25])
    with pytest.raises(FrameProblem, match="no transform is known from the point's frame 'base' to the map frame 'map'"):
        Teaching._to_map(node, point("base", 1.5))
    with pytest.raises(FrameProblem, match="no frame_id"):
        Teaching._to_map(node, point("", 1.5))
    with pytest.raises(ValueError, match="NaN or infinite"):
        Teaching._to_map(node, point("odom", 1.5, (float("inf"), 0.0, 0.0)))


# ------------------------------------------------------------------------------ in order

def test_teaching_an_empty_map_is_refused(h):
    res = h.teach_at("blue mug", h.clicks["conditioner"])
    assert not res.success and "cannot teach yet" in res.message and "map is empty" in res.message, res.message
    assert list(res.taught) == [] and res.name == ""
    res = h.call(h.teach, Teach.Request(name="blue mug", use_current_answer=True))
    assert not res.success and "no current answer" in res.message, res.message
    m = PointStamped()
    m.header.frame_id = "map"
    h.clicked.publish(m)
    wait_for(lambda: "clicked point (0, 0, 0) in 'map' ignored: map is empty" in h.log(), 30, "the refused click")
    assert h.node_a.poll() is None


@need_ros2
def test_click_teach_ground_with_the_ros2_cli(mapped):
    """RViz's click, then naming what it shows, then asking for it by another spelling."""
    h = mapped
    p = h.clicks["conditioner"]
    n_cloud, n_masks = len(h.got["cloud"]), len(h.got["amodal"])
    ros2("topic", "pub", "--once", "/clicked_point", "geometry_msgs/msg/PointStamped",
         "{header: {frame_id: map}, point: %s}" % yaml_point(p))
    wait_for(lambda: re.search(r"clicked \([-0-9., ]+\): \d+ Gaussians, the map thinks it is ", h.log()), 120,
             lambda: f"the click's answer in the log: {h.log()[-1500:]}")
    wait_for(lambda: len(h.got["cloud"]) > n_cloud and len(h.got["amodal"]) > n_masks, 30,
             "the click's cloud and masks")
    clicked = cloud_points(h.got["cloud"][-1])
    assert clicked and h.fresh_status()["clicks"]["answered"] == 1

    n_graph = len(h.got["graph"])
    out = ros2("service", "call", "/rg_node/teach", "rg_interfaces/srv/Teach",
               "{name: 'blue mug', use_current_answer: true}")
    assert "rg_interfaces.srv.Teach_Response(success=True" in out and "name='blue mug'" in out, out[-3000:]
    assert "taught=['blue mug']" in out, out[-3000:]
    wait_for(lambda: len(h.got["cloud"]) > n_cloud + 1, 30, "the taught answer's cloud")
    taught = cloud_points(h.got["cloud"][-1])
    assert overlap(taught, clicked) >= 0.5, (len(taught), len(clicked), overlap(taught, clicked))
    wait_for(lambda: len(h.got["graph"]) > n_graph, 120, "the scene graph republished after teaching")

    out = ros2("service", "call", "/ground", "rg_interfaces/srv/Ground", "{query: 'my mug'}")
    assert "rg_interfaces.srv.Ground_Response(success=True" in out and "taught by a person" in out, out[-3000:]
    assert "target='blue mug'" in out, out[-3000:]
    res = h.call(h.ground, Ground.Request(query="my mug"))
    assert res.success and res.target == "blue mug" and len(res.objects) == 1
    assert overlap(cloud_points(res.cloud), taught) >= 0.9
    h.taught_cloud = taught


@need_ros2
def test_teach_at_a_point_with_the_ros2_cli(mapped):
    h = mapped
    p = h.clicks["orange"]
    out = ros2("service", "call", "/rg_node/teach", "rg_interfaces/srv/Teach",
               "{name: 'lemon', point: {header: {frame_id: map}, point: %s}}" % yaml_point(p))
    assert "Teach_Response(success=True" in out and "taught=['blue mug', 'lemon']" in out, out[-3000:]
    # in another TF frame (map <- table, static): the same object
    res = wait_for(lambda: (lambda r: r if "no transform" not in r.message else None)(
        h.teach_at("lemon", np.asarray(p) - TABLE, frame="table")), 30, "the static transform map <- table")
    assert res.success and res.name == "lemon" and list(res.taught) == ["blue mug", "lemon"], res.message
    box = res.objects[0]
    glo, ghi = h.boxes["orange"]
    olo = np.array([box.aabb_min.x, box.aabb_min.y, box.aabb_min.z])
    ohi = np.array([box.aabb_max.x, box.aabb_max.y, box.aabb_max.z])
    assert np.all(olo <= ghi + 0.05) and np.all(ohi >= glo - 0.05), (olo, ohi, glo, ghi)   # the orange's place


def test_bad_input_is_refused_and_changes_nothing(mapped):
    h = mapped
    before = h.fresh_status()
    n_cloud = len(h.got["cloud"])
    far = np.array([100.0, 0.0, 0.0])
    cases = {"": "empty name", "x" * 65: "65 characters", "blue\x07mug": "control character",
             "42": "holds no letter"}
    for name, expect in cases.items():
        res = h.teach_at(name, h.clicks["shampoo"])
        assert not res.success and expect in res.message, (name, res.message)
        assert list(res.taught) == before["taught"]
    res = h.teach_at("shampoo", [float("nan"), 0.0, 0.0])
    assert not res.success and "NaN or infinite" in res.message, res.message
    res = h.teach_at("shampoo", h.clicks["shampoo"], frame="nowhere")
    assert not res.success and "'nowhere'" in res.message and "no transform is known" in res.message, res.message
    res = h.teach_at("shampoo", h.clicks["shampoo"], frame="")
    assert not res.success and "no frame_id" in res.message, res.message
    res = h.teach_at("shampoo", far)
    assert not res.success and "nothing mapped within 5 cm of (100.000, 0.000, 0.000)" in res.message, res.message
    res = h.call(h.forget, Forget.Request(name="teapot"))
    assert not res.success and "nothing was taught as 'teapot'" in res.message and res.forgotten == 0, res.message
    assert list(res.taught) == before["taught"]
    res = h.call(h.forget, Forget.Request(name=""))
    assert not res.success and "empty name" in res.message
    # clicks: NaN, an unknown frame, far from the map: each counted (and logged, throttled per kind), no new answer
    for key, frame, xyz, expect in (
            ("clicked_point_bad", "map", (float("nan"), 0.0, 0.0), "NaN or infinite"),
            ("clicked_point_frame", "nowhere", (0.0, 0.0, 0.0), "no transform is known from the point's frame 'nowhere'"),
            ("clicked_point", "map", tuple(far), "nothing mapped within 5 cm of (100.000, 0.000, 0.000)")):
        n = h.fresh_status()["input_errors"].get(key, 0)
        m = PointStamped()
        m.header.frame_id = frame
        m.point.x, m.point.y, m.point.z = xyz
        h.clicked.publish(m)
        wait_for(lambda: h.st()["input_errors"].get(key, 0) > n, 60, f"the click refused as {key}")
        if n == 0:   # the first of its kind is logged at once
            assert any(expect in ln and "ignored" in ln and "nothing changed" in ln for ln in h.log().splitlines())
    after = h.fresh_status()
    assert after["gaussians"] == before["gaussians"] and after["taught"] == before["taught"]
    assert after["clicks"]["answered"] == before["clicks"]["answered"]
    assert len(h.got["cloud"]) == n_cloud and h.node_a.poll() is None
    # the current answer is still the last good one: naming it names 'lemon''s object again
    res = h.call(h.teach, Teach.Request(name="lemon", use_current_answer=True))
    assert res.success and list(res.taught) == ["blue mug", "lemon"], res.message


def test_save_then_forget_then_a_restarted_node_still_knows(mapped):
    h = mapped
    res = h.call(h.save, MapFile.Request())
    assert res.success and str(h.saved) in res.message, res.message
    if ROS2 is not None:
        out = ros2("service", "call", "/rg_node/forget", "rg_interfaces/srv/Forget", "{name: 'blue mug'}")
        assert "Forget_Response(success=True" in out and "forgotten=1" in out and "taught=['lemon']" in out, out
    else:
        res = h.call(h.forget, Forget.Request(name="blue mug"))
        assert res.success and res.forgotten == 1 and list(res.taught) == ["lemon"], res.message
    res = h.call(h.ground, Ground.Request(query="my mug"))
    assert "taught by a person" not in res.message and res.target != "blue mug", res.message
    res = h.call(h.forget, Forget.Request(name="blue mug"))
    assert not res.success and "nothing was taught as 'blue mug' (taught: 'lemon')" in res.message, res.message

    log_b = h.tmp / "node_b.log"
    params = write_params(h.tmp / "b.yaml", "rg_node_b", pose_source="topic", load_map=str(h.saved), features=True,
                          train_seconds_max=2.0, torch_threads=1, status_period=0.3, mask_rate=0.0,
                          map_cloud_period=0.0, min_confidence=0.0, scene_graph_period=0.0)
    node_b = start(["node", "--params", str(params), "--name", "rg_node_b",
                    *ros_args({"ground": "/ground_b", "clicked_point": "/b/clicked_point"})], log_b)
    try:
        # its text encoder (the supervision's space) loaded before the first query makes its grounder
        st = wait_for(lambda: node_b.poll() is not None or (h.st("/rg_node_b").get("perception", "loading")
                                                            not in ("loading", "not started") and h.st("/rg_node_b")),
                      120, "node B's models")
        assert node_b.poll() is None and st["perception"] == "ready", (st, h.log(log_b)[-3000:])
        assert st["taught"] == ["blue mug", "lemon"], st
        assert "clicked points /b/clicked_point" in h.log(log_b)
        client = h.node.create_client(Ground, "/ground_b")
        res = h.call(client, Ground.Request(query="the blue mug"))
        assert res.success and res.target == "blue mug" and "taught by a person" in res.message, res.message
        if hasattr(h, "taught_cloud"):   # the group taught through the ros2 CLI, found again after the restart
            assert overlap(cloud_points(res.cloud), h.taught_cloud) >= 0.5
    finally:
        stop(node_b)
    assert h.node_a.poll() is None
