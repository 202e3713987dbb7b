"""The node end to end, two processes on loopback: `rg-node` and `rg-replay` run as subprocesses
(sys.executable, the parent's environment), this process talks to them through rclpy.

Node A (features on, small budgets) serves the module in order: query before any frame, replayed
frames build the map, bad input, a flood, grounding + masks, save, reset. Node B loads A's map at
start-up, sees images without CameraInfo, then maps and is stopped with SIGINT (saving on shutdown).
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # never multicast onto the network
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("ROS_LOG_DIR", str(Path(__file__).resolve().parents[1] / ".ros_log"))
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"

import numpy as np  # noqa: E402
import pytest  # noqa: E402

pytest.importorskip("rg_interfaces.srv", reason="rg_interfaces is not installed: scripts/bootstrap.sh builds it from msg/")
pytest.importorskip("diagnostic_msgs.msg", reason="ros-diagnostic-msgs is not installed (requirements.txt)")

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from rg_interfaces.srv import Ground, MapFile  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from rg_ros import convert as cv  # noqa: E402
from rg_ros import endurance  # noqa: E402
from rg_ros.params import INPUTS  # noqa: E402
from rg_ros.replay import frame_messages  # noqa: E402
from rg_ros.run import NodeExecutor  # noqa: E402

OPTICAL = "camera_color_optical_frame"
TOPICS_A = dict(INPUTS)   # the launch file's remappings, where rg-replay publishes
TOPICS_B = {"rgb/image": "/b/color", "depth/image": "/b/depth", "rgb/camera_info": "/b/info", "pose": "/b/pose"}


def ros_args(remap: dict[str, str]) -> list[str]:
    """--ros-args -r NAME:=TARGET for each entry (the node's relative names set by remapping)."""
    out = ["--ros-args"]
    for name, target in remap.items():
        out += ["-r", f"{name}:={target}"]
    return out


def write_params(path: Path, name: str, **params) -> Path:
    return endurance.write_params(path, params, name)


def start(args: list[str], log: Path, **env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rg_ros.tools", *args], env=dict(os.environ, **env),
                            stdout=log.open("w"), stderr=subprocess.STDOUT)


stop = endurance.stop_process


def is_settled(st: dict) -> bool:
    """The worker has taken every frame it received: mapped, rejected or dropped (none in flight)."""
    return st["mapped"] + st["rejected"] + st["dropped"] == st["received"] and st["queue"] == 0


status_values = endurance.status_values
# tf_wait of the tests whose bags carry every transform: a frame then waits for the TF sample after
# its stamp, which the replayer sends 0.1 s (bag time) later. A drop must mean a missing transform,
# never a replayer or executor stalled by a loaded CPU (2 s was once too short at load average 8). A
# test waiting for a drop on purpose (a frame no transform will ever reach) waits this long first.
TF_WAIT = 10.0


def wait_for(cond, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what() if callable(what) else what}")


class Harness:
    """Node A, the scene, and this process's rclpy side (clients, status and mask subscribers)."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.log_a = tmp / "node_a.log"
        self.save_a = tmp / "map_a.pt"
        params = write_params(tmp / "a.yaml", "rg_node", pose_source="topic", map_width=80, iters_per_keyframe=2, torch_threads=1,
                              frame_queue_size=2, features=True, train_slice=0.5, train_seconds_max=2.0,
                              status_period=0.3, save_path=str(self.save_a), mask_rate=4.0, map_cloud_period=1.0,
                              max_query_chars=2000, camera_info_timeout=3.0,
                              # plumbing: publish the best guess (offline naming of this 80 px map is not
                              # sure of 'orange', rightly: see the xfail below)
                              min_confidence=0.0)
        self.node_a = start(["node", "--params", str(params), *ros_args(TOPICS_A)], self.log_a)
        self.scene = tmp / "scene"   # made while node A starts
        subprocess.run([sys.executable, "-m", "rg_core.cli", "synth", str(self.scene), "--views", "12", "--size",
                        "160x120", "--seed", "3", "--objects", "4", "--json", "--quiet"], env=dict(os.environ),
                       check=True, capture_output=True, timeout=120)
        from rg_core.io.captures import read_scene

        self.frames = read_scene(self.scene).train
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("rg_test_probe", context=self.ctx)
        self.status: dict[str, dict] = {}
        self.msgs: dict[str, list] = {"amodal": [], "visible": [], "grounded": [], "markers": []}
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_status, 10)
        self.node.create_subscription(Image, "/rg_node/amodal_mask", lambda m: self.msgs["amodal"].append(m), 10)
        self.node.create_subscription(Image, "/rg_node/visible_mask", lambda m: self.msgs["visible"].append(m), 10)
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        self.node.create_subscription(PointCloud2, "/rg_node/grounded_cloud", lambda m: self.msgs["grounded"].append(m), 10)
        self.node.create_subscription(MarkerArray, "/rg_node/markers", lambda m: self.msgs["markers"].append(m), 10)
        self.ground = self.node.create_client(Ground, "/ground")
        self.save = self.node.create_client(MapFile, "/rg_node/save_map")
        self.reset = self.node.create_client(Trigger, "/rg_node/reset")
        self.pubs: dict[str, list] = {}
        self.executor = NodeExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_for(lambda: self.st() or self.node_a.poll() is not None, 120, "node A's first status")
        assert self.node_a.poll() is None, f"rg-node exited {self.node_a.returncode}:\n{self.log()[-3000:]}"

    def _on_status(self, msg: DiagnosticArray) -> None:
        self.status.update(status_values(msg))

    def st(self, name: str = "/rg_node") -> dict:
        return self.status.get(name, {})

    def fresh_status(self, name: str = "/rg_node", timeout: float = 10.0, settled: bool = False) -> dict:
        """A status sent after now; settled: also every frame received is mapped, rejected or dropped."""
        t = time.monotonic()

        def ok():
            st = self.st(name)
            return st if st.get("_t", 0) > t and (not settled or is_settled(st)) else None
        return wait_for(ok, timeout if not settled else max(timeout, 60.0), f"status of {name}")

    def call(self, client, req, timeout: float = 60.0):
        assert client.wait_for_service(timeout_sec=30), f"{client.srv_name} not discovered"
        res = client.call(req, timeout_sec=timeout)
        assert res is not None, f"{client.srv_name}: no reply within {timeout} s"
        return res

    def publishers(self, prefix: str = ""):
        key = prefix or "a"
        if key not in self.pubs:
            t = TOPICS_B if prefix else TOPICS_A
            q = qos_profile_sensor_data
            self.pubs[key] = [self.node.create_publisher(Image, t["rgb/image"], q),
                              self.node.create_publisher(Image, t["depth/image"], q),
                              self.node.create_publisher(CameraInfo, t["rgb/camera_info"], q),
                              self.node.create_publisher(PoseStamped, t["pose"], q)]
            wait_for(lambda: all(p.get_subscription_count() > 0 for p in self.pubs[key]), 10, "node subscriptions")
        return self.pubs[key]

    def publish(self, msgs, prefix: str = "", skip_info: bool = False) -> None:
        for i, (pub, m) in enumerate(zip(self.publishers(prefix), msgs)):
            if not (skip_info and i == 2):
                pub.publish(m)

    def frame(self, i: int = 0):
        return frame_messages(self.frames[i % len(self.frames)], self.node.get_clock().now().to_msg(), OPTICAL, "map")

    def log(self, path: Path | None = None) -> str:
        return (path or self.log_a).read_text(errors="replace")

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5)
        self.node.destroy_node()
        self.ctx.try_shutdown()
        self.thread.join(timeout=5)
        stop(self.node_a)


@pytest.fixture(scope="module")
def h(tmp_path_factory):
    harness = Harness(tmp_path_factory.mktemp("rgnode"))
    try:
        yield harness
    finally:
        harness.close()


# ------------------------------------------------------------------------------ node A, in order

def test_query_before_any_frame_and_bad_queries(h):
    res = h.call(h.ground, Ground.Request(query="the orange"))
    assert not res.success and "map is empty" in res.message and len(res.objects) == 0
    assert res.cloud.header.frame_id == "map"
    res = h.call(h.ground, Ground.Request(query="   "))
    assert not res.success and "empty query" in res.message
    res = h.call(h.ground, Ground.Request(query="x" * (1 << 20)))
    assert not res.success and "1048576 characters" in res.message and "max_query_chars" in res.message
    res = h.call(h.ground, Ground.Request(query="orange", mode="telepathic"))
    assert not res.success and "'telepathic'" in res.message
    assert h.node_a.poll() is None


def replay_scene(h) -> dict:
    """`rg-replay` of the scene into node A; the status once it holds keyframes and an empty queue."""
    rep = subprocess.run([sys.executable, "-m", "rg_ros.tools", "replay", str(h.scene), "--rate", "4"],
                         env=dict(os.environ), capture_output=True, text=True, timeout=60)
    assert rep.returncode == 0, rep.stdout + rep.stderr
    assert f"published {len(h.frames)} frames" in rep.stdout + rep.stderr
    return wait_for(lambda: h.st() if h.st().get("keyframes", 0) > 0 and h.st()["queue"] == 0 else None, 60,
                    "keyframes in the status")


def test_replayed_frames_build_the_map(h):
    replay_scene(h)
    st = h.fresh_status(settled=True)
    # Sensor QoS is best effort: how many replayed frames arrive, and how many a busy machine drops
    # from the 2-frame queue, is up to DDS and the load. What the node guarantees: every frame it
    # received is mapped, rejected or dropped and counted, and the map holds what it mapped.
    assert st["frames"] >= 1 and st["gaussians"] > 0 and st["queue_size"] == 2
    assert st["mapped"] + st["dropped"] + st["rejected"] == st["received"] >= st["frames"]
    assert st["rejected"] == 0 and set(st["input_errors"]) <= {"queue_drop"}   # mapping may lag the replay


@pytest.mark.parametrize("case", ["encoding", "sizes", "nan_pose", "quaternion", "pose_frame"])
def test_bad_input_keeps_node_and_map(h, case):
    before = h.fresh_status(settled=True)   # not while the last good frame is still being mapped
    color, depth, info, pose = h.frame(0)
    expect = {"encoding": "colour image rejected", "sizes": "colour is 160x120 but depth is 80x60",
              "nan_pose": "NaN", "quaternion": "quaternion norm", "pose_frame": "pose is in frame 'odom'"}[case]
    if case == "encoding":
        color = cv.to_image(np.zeros((120, 160), np.uint16), "16UC1", OPTICAL, color.header.stamp)
    elif case == "sizes":
        depth = cv.to_image(np.full((60, 80), 500, np.uint16), "16UC1", OPTICAL, depth.header.stamp)
    elif case == "nan_pose":
        pose.pose.position.x = float("nan")
    elif case == "quaternion":
        q = pose.pose.orientation
        q.x, q.y, q.z, q.w = 2 * q.x, 2 * q.y, 2 * q.z, 2 * q.w   # scaled: not a rotation
    else:
        pose.header.frame_id = "odom"
    def send_until_logged():   # best effort under load: resend with a fresh stamp until the node says it
        stamp = h.node.get_clock().now().to_msg()
        for m in (color, depth, info, pose):
            m.header.stamp = stamp
        h.publish((color, depth, info, pose))
        return expect in h.log()

    wait_for(send_until_logged, 30, f"'{expect}' in the node log")
    after = h.fresh_status()
    assert after["frames"] == before["frames"] and after["keyframes"] == before["keyframes"]
    assert after["gaussians"] == before["gaussians"] and h.node_a.poll() is None


def test_flood_is_dropped_and_bounded(h):
    """40 frames at once, each of an area the map has not seen (the scene shifted 5 m further each
    time, so every mapped one is a keyframe: tens of ms against well under 1 ms to publish one): the
    queue of 2 drops and says so. The map is then reset and rebuilt for the tests after this one."""
    import copy

    before = h.fresh_status()
    burst = []
    for i in range(40):
        f = copy.copy(h.frames[i % len(h.frames)])
        f.cam_to_world = f.cam_to_world.copy()
        f.cam_to_world[0, 3] += 5.0 * (i + 1)
        burst.append(frame_messages(f, h.node.get_clock().now().to_msg(), OPTICAL, "map"))
    for msgs in burst:
        h.publish(msgs)
    st = wait_for(lambda: h.st() if h.st().get("dropped", 0) > before["dropped"] else None, 20, "dropped frames")
    assert st["queue"] <= st["queue_size"] == 2
    assert "mapping is slower than the input" in h.log()
    wait_for(lambda: h.st()["queue"] == 0, 60, "the queue to drain")
    assert h.node_a.poll() is None
    assert h.call(h.reset, Trigger.Request()).success
    assert replay_scene(h)["gaussians"] > 0



def test_ground_publishes_masks_cloud_and_markers(h):
    res = h.call(h.ground, Ground.Request(query="orange"))
    if "grounding not available" in res.message:
        assert not res.success
        pytest.xfail(res.message)
    # features: supervision and a few seconds of field training when idle
    wait_for(lambda: h.st().get("field_stop") and h.st().get("queue") == 0, 240,
             lambda: f"field training (status {h.st()})")
    res = h.call(h.ground, Ground.Request(query="orange", max_results=1), timeout=120)
    assert res.success, res.message
    assert len(res.objects) >= 1 and res.cloud.width > 0
    wait_for(lambda: h.msgs["amodal"] and h.msgs["visible"] and h.msgs["markers"] and h.msgs["grounded"], 20,
             "masks, markers and the grounded cloud")
    for m in (h.msgs["amodal"][-1], h.msgs["visible"][-1]):
        assert m.encoding == "mono8" and (m.width, m.height) == (160, 120) and m.header.frame_id == OPTICAL
        assert set(np.unique(cv.image_to_mask(m))) <= {0, 255}
    from visualization_msgs.msg import Marker

    kinds = {mk.type for mk in h.msgs["markers"][-1].markers}
    assert {Marker.CUBE, Marker.LINE_LIST, Marker.TEXT_VIEW_FACING} <= kinds
    assert h.msgs["grounded"][-1].header.frame_id == "map" and h.msgs["grounded"][-1].width == res.cloud.width


def test_relational_query_publishes_the_scene_graph(h):
    """A counting query goes over the scene graph, with the robot's camera for view-dependent words;
    the graph then arrives latched on ~/scene_graph (a subscriber that joins late gets it) with its
    text markers."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rg_interfaces.msg import SceneGraph
    from visualization_msgs.msg import MarkerArray

    res = h.call(h.ground, Ground.Request(query="how many objects are there"), timeout=180)
    if "grounding not available" in res.message:
        pytest.xfail(res.message)
    assert "graph" in res.stage_names, (res.message, list(res.stage_names))
    near = h.call(h.ground, Ground.Request(query="the object nearest to me"), timeout=60)
    assert "the robot's current camera" in near.explanation or not near.success, near.message
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    got: dict[str, list] = {"graph": [], "labels": []}
    h.node.create_subscription(SceneGraph, "/rg_node/scene_graph", lambda m: got["graph"].append(m), latched)
    h.node.create_subscription(MarkerArray, "/rg_node/scene_graph_markers", lambda m: got["labels"].append(m), latched)
    wait_for(lambda: got["graph"] and got["labels"], 30, "the latched scene graph and its labels")
    g = got["graph"][-1]
    assert g.header.frame_id == "map" and abs(np.linalg.norm([g.up.x, g.up.y, g.up.z]) - 1) < 1e-5
    assert len(g.objects) == (len(res.objects) if res.success else 0), (res.message, [o.name for o in g.objects])
    assert len(got["labels"][-1].markers) == len(g.objects) + 1           # DELETEALL, then one label each


@pytest.mark.xfail(strict=False, reason="offline ConSE supervision does not recognise the rendered orange: "
                   "at the node's 80 px map its masks are the best match for 'orange' in 0 of 7 keyframes (the "
                   "orange table top is, through the colour term); measured 1% of the cloud inside its box, "
                   "target 80%. The 3D part passes with oracle supervision (rg eval --supervision oracle)")
def test_grounded_cloud_lies_in_the_targets_box(h):
    """The answer is the right object: the cloud's points lie in its ground-truth box (1 cm margin),
    for the explicit query and for an implicit one."""
    from rg_core.io.captures import read_scene
    from rg_ros.pointcloud import from_pointcloud2

    box = {o.name: o for o in read_scene(h.scene).objects}["orange"]
    res = h.call(h.ground, Ground.Request(query="orange"), timeout=120)
    implicit = h.call(h.ground, Ground.Request(query="a round citrus fruit with a thick peel"), timeout=120)
    # The orange lies in the last replayed camera's view: a right answer shows in its amodal mask
    # (the mask test above only checks format: a wrong group may lie outside the view).
    wait_for(lambda: h.msgs["amodal"], 20, "an amodal mask")
    assert cv.image_to_mask(h.msgs["amodal"][-1]).any()
    for r in (res, implicit):
        assert r.success, r.message
        pts, _ = from_pointcloud2(r.cloud)
        inside = np.all((pts >= np.array(box.aabb_min) - 0.01) & (pts <= np.array(box.aabb_max) + 0.01), 1)
        print(f"{r.target}: {inside.mean():.2f} of {len(pts)} points inside the orange's box")
        assert inside.mean() >= 0.8, (r.target, r.explanation, inside.mean())


def test_save_map_writes_a_loadable_map(h):
    from rg_core.map.store import load_map

    res = h.call(h.save, MapFile.Request())
    assert res.success and str(h.save_a) in res.message
    m = load_map(h.save_a)
    assert len(m.keyframes) > 0 and len(m.gaussians) > 0


# ------------------------------------------------------------------------------ node B

def test_start_up_map_missing_camera_info_and_sigint_save(h):
    from rg_core.map.store import load_map

    assert h.save_a.is_file(), "needs the map saved by the previous test"
    loaded = load_map(h.save_a)
    log_b, save_b = h.tmp / "node_b.log", h.tmp / "map_b.pt"
    params = write_params(h.tmp / "b.yaml", "rg_node_b", pose_source="topic", load_map=str(h.save_a),
                          features=False, save_on_shutdown=True, save_path=str(save_b), map_width=80,
                          iters_per_keyframe=2, torch_threads=1, status_period=0.3, camera_info_timeout=1.0,
                          preset="paper")
    # the paper preset with an empty model cache: the node starts, says which command fetches the LVLM,
    # and answers implicit queries with the text reasoner
    models = h.tmp / "no_models"
    models.mkdir(exist_ok=True)
    node_b = start(["node", "--params", str(params), "--name", "rg_node_b", *ros_args(TOPICS_B | {"ground": "/ground_b"})],
                   log_b, RG_MODELS_DIR=str(models))
    try:
        st = wait_for(lambda: h.st("/rg_node_b") or None, 60, "node B status")
        log = h.log(log_b)
        assert "preset 'paper' reasons with llava-1.5-7b" in log and "rg models fetch llava-1.5-7b" in log, log[-2000:]
        assert "implicit queries use the text reasoner" in log
        assert st["keyframes"] == len(loaded.keyframes) and st["gaussians"] == len(loaded.gaussians)
        frames0 = st["frames"]
        # images and poses but no CameraInfo: nothing is mapped, and the log says why
        def send_without_info():
            h.publish(h.frame(0), prefix="b", skip_info=True)
            return "no CameraInfo on /b/info" in h.log(log_b)

        wait_for(send_without_info, 30, "the missing CameraInfo warning")
        assert h.fresh_status("/rg_node_b")["frames"] == frames0 and node_b.poll() is None
        # now complete frames; stop with SIGINT while it maps
        for i in range(4):
            h.publish(h.frame(i + 3), prefix="b")
            time.sleep(0.1)
        wait_for(lambda: h.st("/rg_node_b")["received"] > 0, 30, "node B to receive frames")
        t = time.monotonic()
        code = stop(node_b, timeout=60)
        assert code == 0, f"exit code {code}\n{h.log(log_b)[-3000:]}"
        assert time.monotonic() - t < 60
        assert "map saved on shutdown" in h.log(log_b)
        saved = load_map(save_b)
        assert saved.frames_seen >= len(loaded.keyframes) and len(saved.keyframes) >= len(loaded.keyframes)
    finally:
        stop(node_b)


def test_reset_empties_the_map(h):
    res = h.call(h.reset, Trigger.Request())
    assert res.success and "reset" in res.message
    st = h.fresh_status()
    assert st["keyframes"] == 0 and st["gaussians"] == 0
    res = h.call(h.ground, Ground.Request(query="orange"))
    assert not res.success and "map is empty" in res.message


def test_sigint_stops_node_a_cleanly(h):
    assert h.node_a.poll() is None
    assert stop(h.node_a, timeout=60) == 0, h.log()[-3000:]
    assert "shutting down" in h.log()
