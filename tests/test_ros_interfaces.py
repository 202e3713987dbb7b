"""rg_interfaces (built from msg/ by scripts/bootstrap.sh): GroundingResult -> Ground.Response and a
real two-node service round trip on loopback, in one process."""
from __future__ import annotations

import os
import random
import threading
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # never multicast onto the network
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("ROS_LOG_DIR", str(Path(__file__).resolve().parents[1] / ".ros_log"))

import numpy as np  # noqa: E402
import pytest  # noqa: E402

pytest.importorskip("rg_interfaces.srv", reason="rg_interfaces is not installed: scripts/bootstrap.sh builds it from msg/")

import rclpy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from rg_interfaces.msg import GroundedObject as GroundedObjectMsg  # noqa: E402
from rg_interfaces.srv import Ground  # noqa: E402

from rg_core.grounding.result import GroundedObject, GroundingResult  # noqa: E402
from rg_core.perception.query import parse_mode  # noqa: E402
from rg_ros import convert as cv  # noqa: E402
from rg_ros.pointcloud import from_pointcloud2  # noqa: E402
from rg_ros.run import NodeExecutor  # noqa: E402


def rot_z(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def make_object(n: int, center, deg: float, seed: int, confidence: float = 0.8) -> GroundedObject:
    rng = np.random.default_rng(seed)
    pts = (rng.normal(size=(n, 3)) * 0.05 + center).astype(np.float32)
    return GroundedObject(
        gaussian_ids=np.arange(n, dtype=np.int64) + seed * 1000, points=pts,
        colors=rng.integers(0, 256, (n, 3), dtype=np.uint8),
        aabb_min=pts.min(0).astype(np.float64), aabb_max=pts.max(0).astype(np.float64),
        obb_center=np.asarray(center, np.float64), obb_rotation=rot_z(deg),
        obb_extent=np.array([0.2, 0.1, 0.3]), confidence=confidence)


def make_result(query: str = "the red mug") -> GroundingResult:
    return GroundingResult(
        success=True, message="1 object", query=query, target="mug", explanation="red and on the table",
        confidence=0.75, objects=[make_object(40, [1.0, 2.0, 0.5], 90.0, 1), make_object(7, [0.0, -1.0, 0.2], 30.0, 2)],
        timings={"reason": 0.5, "select": 0.02, "render": 0.125}, reference_view=3)


def check_response(res, result: GroundingResult) -> None:
    assert res.success and res.message == result.message and res.target == "mug"
    assert res.explanation == result.explanation and res.confidence == pytest.approx(0.75)
    assert list(res.stage_names) == ["reason", "select", "render"]
    np.testing.assert_allclose(res.stage_seconds, [0.5, 0.02, 0.125])
    assert len(res.objects) == 2
    for msg, obj in zip(res.objects, result.objects):
        assert msg.gaussian_count == len(obj.gaussian_ids) and msg.confidence == pytest.approx(obj.confidence)
        T = cv.pose_to_matrix(msg.pose)
        np.testing.assert_allclose(T[:3, :3], obj.obb_rotation, atol=1e-9)
        np.testing.assert_allclose(T[:3, 3], obj.obb_center)
        np.testing.assert_allclose([msg.size.x, msg.size.y, msg.size.z], obj.obb_extent)
        np.testing.assert_allclose([msg.aabb_min.x, msg.aabb_min.y, msg.aabb_min.z], obj.aabb_min)
        np.testing.assert_allclose([msg.aabb_max.x, msg.aabb_max.y, msg.aabb_max.z], obj.aabb_max)
    assert res.cloud.header.frame_id == "map"
    pts, cols = from_pointcloud2(res.cloud)
    np.testing.assert_array_equal(pts, np.concatenate([o.points for o in result.objects]))
    np.testing.assert_array_equal(cols, np.concatenate([o.colors for o in result.objects]))


# ------------------------------------------------------------------------------ conversion

def make_graph():
    """A table with a mug resting on it and a ball beside the table (z up), as a scene graph."""
    from rg_core.grounding.relations import SceneObject, graph_relations

    def box(name, lo, hi, colour, seed):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        pts = (lo + np.random.default_rng(seed).random((100, 3)) * (hi - lo)).astype(np.float32)
        o = GroundedObject(np.arange(100) + 100 * seed, pts, np.zeros((100, 3), np.uint8), lo, hi, (lo + hi) / 2,
                           np.eye(3), hi - lo, 0.9)
        return SceneObject([(name, 0.9), (name.split()[-1] + "s", 0.4)], o, colour)

    objs = [box("table", [-0.5, -0.4, 0.0], [0.5, 0.4, 0.7], "brown", 0),
            box("red mug", [0.0, 0.0, 0.7], [0.08, 0.08, 0.8], "red", 1),
            box("ball", [0.55, 0.0, 0.0], [0.65, 0.1, 0.1], "orange", 2)]
    up = np.array([0.0, 0.0, 1.0])
    return objs, graph_relations(objs, up), up


def test_scene_graph_message_and_markers():
    from rg_interfaces.msg import SceneGraph

    from rg_ros.markers import GRAPH_NS, graph_markers

    objs, rels, up = make_graph()
    assert (1, "on", 0) in [r[:3] for r in rels] and (0, "near", 2) in [r[:3] for r in rels], rels
    msg = deserialize_message(serialize_message(cv.graph_to_msg(objs, rels, up, "map", 3.0)), SceneGraph)
    assert msg.header.frame_id == "map" and [msg.up.x, msg.up.y, msg.up.z] == [0.0, 0.0, 1.0]
    assert [o.name for o in msg.objects] == ["table", "red mug", "ball"] and msg.objects[1].colour == "red"
    assert list(msg.objects[1].names) == ["red mug", "mugs"] and msg.objects[1].name_confidences[1] == pytest.approx(0.4)
    assert msg.objects[0].gaussian_count == 100 and msg.objects[0].aabb_max.z == pytest.approx(0.7)
    on = [(r.subject, r.object) for r in msg.relations if r.predicate == "on"]
    assert on == [(1, 0)]
    with pytest.raises(ValueError, match="outside"):
        cv.graph_to_msg(objs, [(0, "on", 7, 0.0)], up, "map")
    m = graph_markers(objs, up, "map").markers
    assert m[0].action == m[0].DELETEALL and m[0].ns == GRAPH_NS
    assert [x.text for x in m[1:]] == ["table (brown)", "red mug (red)", "ball (orange)"]
    assert m[2].pose.position.z > 0.8                             # above the mug's top along up



def test_result_to_response_survives_serialization():
    result = make_result()
    res = cv.result_to_response(result, "map", 7.5)
    assert cv.from_time(res.cloud.header.stamp) == 7.5
    res = deserialize_message(serialize_message(res), Ground.Response)
    check_response(res, result)


def test_teach_and_forget_services_survive_serialization():
    """Teach.srv / Forget.srv (point and teach, rg_ros/teaching.py): the request's PointStamped and
    flag, the answer's fields (the same conversion as Ground's), the taught names."""
    from rg_interfaces.srv import Forget, Teach

    req = Teach.Request(name="blue mug", use_current_answer=False)
    req.point.header.frame_id, req.point.point.x, req.point.point.z = "table", 0.25, -1.5
    req = deserialize_message(serialize_message(req), Teach.Request)
    assert (req.name, req.point.header.frame_id, req.point.point.x, req.point.point.z) == ("blue mug", "table", 0.25, -1.5)
    assert req.use_current_answer is False and Teach.Request(use_current_answer=True).use_current_answer
    result = make_result("blue mug")
    res = cv.answer_fields(result, "map", 7.5, Teach.Response())
    res.name, res.taught = "blue mug", ["blue mug", "lemon"]
    res = deserialize_message(serialize_message(res), Teach.Response)
    assert res.success and res.message == result.message and res.name == "blue mug"
    assert res.explanation == result.explanation and res.confidence == pytest.approx(0.75)
    assert len(res.objects) == 2 and res.objects[0].gaussian_count == 40 and list(res.taught) == ["blue mug", "lemon"]
    pts, _ = from_pointcloud2(res.cloud)
    np.testing.assert_array_equal(pts, np.concatenate([o.points for o in result.objects]))
    assert not hasattr(res, "stage_names") and not hasattr(res, "target")
    f = Forget.Response(success=True, message="forgot 1", forgotten=1, taught=["lemon"])
    f = deserialize_message(serialize_message(f), Forget.Response)
    assert f.success and f.forgotten == 1 and list(f.taught) == ["lemon"]
    assert deserialize_message(serialize_message(Forget.Request(name="my mug")), Forget.Request).name == "my mug"


def test_abstained_answer_keeps_its_best_guess():
    """An answer below the confidence threshold: success false and why, and the best guess's objects
    and cloud for a client that wants to look at it."""
    result = make_result()
    result.success, result.message = False, "not sure the answer is 'mug': confidence 0.12 < 0.46 (...)"
    res = deserialize_message(serialize_message(cv.result_to_response(result, "map", 7.5)), Ground.Response)
    assert not res.success and res.message.startswith("not sure") and len(res.objects) == 2
    assert res.cloud.width == sum(len(o.points) for o in result.objects)


def test_failed_result_has_empty_cloud():
    res = cv.result_to_response(GroundingResult(success=False, message="map is empty"), "map")
    assert not res.success and res.message == "map is empty" and len(res.objects) == 0
    assert res.cloud.width == 0 and res.cloud.header.frame_id == "map"
    pts, cols = from_pointcloud2(deserialize_message(serialize_message(res), Ground.Response).cloud)
    assert pts.shape == (0, 3) and cols.shape == (0, 3)


def test_reflected_or_broken_obb_frames():
    obj = make_object(5, [0, 0, 0], 10.0, 3)
    obj.obb_rotation = obj.obb_rotation * np.array([1.0, 1.0, -1.0])   # left-handed: same box
    msg = cv.object_to_msg(obj)
    assert isinstance(msg, GroundedObjectMsg)
    R = cv.pose_to_matrix(msg.pose)[:3, :3]
    np.testing.assert_allclose(R[:, :2], obj.obb_rotation[:, :2], atol=1e-9)
    np.testing.assert_allclose(R[:, 2], -obj.obb_rotation[:, 2], atol=1e-9)
    obj.obb_rotation = np.eye(3) * 2
    with pytest.raises(ValueError, match="orthonormal"):
        cv.object_to_msg(obj)
    obj.obb_rotation = np.full((3, 3), np.nan)
    with pytest.raises(ValueError, match="NaN"):
        cv.object_to_msg(obj)


def test_float32_pca_rotation_is_made_exact():
    obj = make_object(5, [0, 0, 0], 37.0, 4)
    obj.obb_rotation = obj.obb_rotation.astype(np.float32) + 1e-4   # what a PCA in float32 might give
    q = cv.object_to_msg(obj).pose.orientation
    assert abs(np.linalg.norm([q.x, q.y, q.z, q.w]) - 1) < 1e-12


# ------------------------------------------------------------------------- service round trip

@pytest.fixture
def ros_context():
    """A fresh rclpy Context per test; shut down even if the test fails."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    ctx.try_shutdown()


def serve(ctx, handler):
    """Server and client nodes spun by NodeExecutor (rg_ros.run) in a daemon thread."""
    server = rclpy.create_node("rg_test_server", context=ctx)
    client_node = rclpy.create_node("rg_test_client", context=ctx)
    server.create_service(Ground, "ground", handler)
    client = client_node.create_client(Ground, "ground")
    executor = NodeExecutor(context=ctx)
    executor.add_node(server)
    executor.add_node(client_node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()

    def close():
        executor.shutdown(timeout_sec=5)
        client_node.destroy_client(client)
        server.destroy_node()
        client_node.destroy_node()
        thread.join(timeout=5)

    return client, close


def ground_handler(request, response):
    """What the node will do, minus the map: parse the request, answer with a converted result."""
    try:
        mode = parse_mode(request.mode)
    except ValueError as e:
        return cv.result_to_response(GroundingResult(success=False, message=str(e), query=request.query),
                                     "map", response=response)
    result = make_result(request.query)
    result.explanation = f"{mode}: {result.explanation}"
    if request.max_results:
        result.objects = result.objects[: request.max_results]
    return cv.result_to_response(result, "map", 42.0, response=response)


def test_ground_service_round_trip(ros_context):
    client, close = serve(ros_context, ground_handler)
    try:
        assert client.wait_for_service(timeout_sec=10), "Ground service not discovered on loopback"
        res = client.call(Ground.Request(query="the red mug", mode=""), timeout_sec=10)
        assert res is not None, "no reply within 10 s"
        result = make_result()
        result.explanation = "auto: " + result.explanation
        check_response(res, result)
        assert cv.from_time(res.cloud.header.stamp) == 42.0

        res = client.call(Ground.Request(query="mug", mode="implicit", max_results=1), timeout_sec=10)
        assert res.success and len(res.objects) == 1 and res.explanation.startswith("implicit: ")
        assert res.cloud.width == 40

        res = client.call(Ground.Request(query="mug", mode="telepathic"), timeout_sec=10)
        assert not res.success and "'telepathic'" in res.message and len(res.objects) == 0
    finally:
        close()


def test_fresh_context_per_test_also_works(ros_context):
    """A second test with its own context: nothing of the first one's graph leaks into it."""
    client, close = serve(ros_context, ground_handler)
    try:
        assert client.wait_for_service(timeout_sec=10)
        res = client.call(Ground.Request(query="x"), timeout_sec=10)
        assert res is not None and res.success and len(res.objects) == 2
    finally:
        close()


@pytest.mark.parametrize("msg", ["TFMessage", "TF2Error"])
def test_tf2_msgs_type_hash_matches_kilted(msg):
    """The tf2_msgs this project builds (msg_tf2/, when no tf2_msgs is importable) or the one a full
    ROS 2 install brings must carry Kilted's type hash, or real graphs and bags would not talk to the node."""
    import json

    pytest.importorskip("tf2_msgs.msg")
    typesys = pytest.importorskip("rosbags.typesys")
    import sys

    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [sys.prefix]
    found = [Path(p) / "share" / "tf2_msgs" / "msg" / f"{msg}.json" for p in prefixes]
    found = [f for f in found if f.is_file()]
    assert found, f"no share/tf2_msgs/msg/{msg}.json under {prefixes}"
    desc = json.loads(found[0].read_text())
    ours = desc["type_hashes"][0]
    assert ours["type_name"] == f"tf2_msgs/msg/{msg}"
    kilted = typesys.get_typestore(typesys.Stores.ROS2_KILTED)
    assert ours["hash_string"] == kilted.hash_rihs01(f"tf2_msgs/msg/{msg}")
