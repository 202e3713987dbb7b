"""ROS 2 bags, headless (rg_core.io.rosbag, ros_images, rosbag_write; `rg map BAG`): a real mcap bag
written from box_toys_50 with the RealSense topics and the TF tree map -> odom -> base_link
(dynamic) -> camera_link -> camera_color_optical_frame (static), read back through rosbags."""
from __future__ import annotations

import json
import math
import struct

import cv2
import numpy as np
import pytest

from rg_core.io import ros_images as ri
from rg_core.io.captures import read_scene
from rg_core.io.images import SceneError
from rg_core.io.rosbag import BagOptions, is_bag, read_bag
from rg_core.io.rosbag_write import COLOR_TOPIC, DEPTH_TOPIC, INFO_TOPIC, write_scene_bag

from conftest import need_rgbd

pytest.importorskip("rosbags")
N_FRAMES = 10


@pytest.fixture(scope="module")
def frames():
    return read_scene(need_rgbd("box_toys_50"), test_every=0).train[:N_FRAMES]


@pytest.fixture(scope="module")
def bag(frames, tmp_path_factory):
    return write_scene_bag(frames, tmp_path_factory.mktemp("bag") / "box_toys")


def rewrite(src, dst, fn):
    """Copy bag `src` to `dst` passing each (topic, message) through fn -> message or None (dropped)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_KILTED)
    with AnyReader([src]) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for conn, t, raw in reader.messages():
            msg = fn(conn.topic, reader.deserialize(raw, conn.msgtype))
            if msg is None:
                continue
            if conn.topic not in conns:
                conns[conn.topic] = writer.add_connection(conn.topic, conn.msgtype, typestore=ts)
            writer.write(conns[conn.topic], t, ts.serialize_cdr(msg, conn.msgtype))
    return dst


# ------------------------------------------------------------------------------ reading

def test_bag_reads_back_the_scene(bag, frames):
    assert is_bag(bag) and is_bag(next(bag.glob("*.mcap"))) and not is_bag(bag.parent)
    scene = read_bag(bag, test_every=0)
    assert scene.kind == "rosbag2" and len(scene.train) == N_FRAMES and scene.info["dropped"] == {}
    assert scene.info["topics"]["color"] == COLOR_TOPIC and scene.info["topics"]["depth"] == DEPTH_TOPIC
    assert scene.info["topics"]["info"] == INFO_TOPIC and scene.info["topics"]["tf_static"] == ["/tf_static"]
    for got, want in zip(scene.train, frames):
        # the pose came through four links, one of them interpolated between 10 Hz samples
        np.testing.assert_allclose(got.cam_to_world, want.cam_to_world, atol=1e-9)
        np.testing.assert_allclose(got.intrinsics.K, want.intrinsics.K)
    f, g = scene.train[4], frames[4]
    np.testing.assert_allclose(f.load_depth(), g.load_depth(), atol=1e-6)   # compressedDepth PNG is lossless
    err = np.abs(f.load_rgb().astype(np.int16) - g.load_rgb())
    assert err.mean() < 3.0 and err.max() < 80   # JPEG quality 95
    # the .mcap file alone (no metadata.yaml) reads the same
    single = read_bag(next(bag.glob("*.mcap")), test_every=4)
    assert len(single.train) + len(single.test) == N_FRAMES and len(single.test) == 3


def test_raw_image_bag_is_lossless(frames, tmp_path):
    """Uncompressed sensor_msgs/Image (bgr8, 16UC1) on the raw RealSense topics, auto-detected."""
    b = write_scene_bag(frames[:3], tmp_path / "raw", raw=True)
    scene = read_bag(b, test_every=0)
    assert scene.info["topics"]["color"] == COLOR_TOPIC.rsplit("/", 1)[0] and len(scene.train) == 3
    np.testing.assert_array_equal(scene.train[1].load_rgb(), frames[1].load_rgb())
    np.testing.assert_allclose(scene.train[1].load_depth(), frames[1].load_depth(), atol=1e-6)


def test_sqlite3_bag_and_odometry_and_topic_pose_sources(frames, tmp_path):
    """db3 storage; pose_source topic (PoseStamped) and odometry (nav_msgs/Odometry + static TF)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_KILTED)
    db3 = write_scene_bag(frames[:4], tmp_path / "db3bag", storage="sqlite3")
    assert next(db3.glob("*.db3"))
    assert len(read_bag(db3, test_every=0).train) == 4
    # add /camera/pose (PoseStamped of the optical frame in map) and /odom (map <- base_link)
    from rg_core.geometry.rotations import rot_to_quat
    from rg_core.io.rosbag_write import base_from_optical

    M = ts.types
    stamps = {}

    def add(topic, msg):
        if topic == COLOR_TOPIC:
            stamps[len(stamps)] = msg.header.stamp
        return msg

    src = write_scene_bag(frames[:4], tmp_path / "src")
    rewrite(src, tmp_path / "copy", add)
    from rosbags.rosbag2 import StoragePlugin, Writer

    out = tmp_path / "poses"
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        from rosbags.highlevel import AnyReader

        with AnyReader([src]) as r:
            conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in r.connections}
            for conn, t, raw in r.messages():
                w.write(conns[conn.topic], t, raw)
        cp = w.add_connection("/camera/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        co = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        for i, f in enumerate(frames[:4]):
            st = stamps[i]
            T = f.cam_to_world
            q = rot_to_quat(T[:3, :3])
            pose = M["geometry_msgs/msg/Pose"](position=M["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                               orientation=M["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
            hdr = M["std_msgs/msg/Header"](stamp=st, frame_id="map")
            ns = st.sec * 10**9 + st.nanosec
            w.write(cp, ns, ts.serialize_cdr(M["geometry_msgs/msg/PoseStamped"](header=hdr, pose=pose),
                                             "geometry_msgs/msg/PoseStamped"))
            Tb = T @ np.linalg.inv(base_from_optical())   # map <- base_link
            qb = rot_to_quat(Tb[:3, :3])
            bpose = M["geometry_msgs/msg/Pose"](position=M["geometry_msgs/msg/Point"](x=Tb[0, 3], y=Tb[1, 3], z=Tb[2, 3]),
                                                orientation=M["geometry_msgs/msg/Quaternion"](x=qb[0], y=qb[1], z=qb[2], w=qb[3]))
            cov = M["geometry_msgs/msg/PoseWithCovariance"](pose=bpose, covariance=np.zeros(36))
            tw = M["geometry_msgs/msg/TwistWithCovariance"](
                twist=M["geometry_msgs/msg/Twist"](linear=M["geometry_msgs/msg/Vector3"](x=0, y=0, z=0),
                                                   angular=M["geometry_msgs/msg/Vector3"](x=0, y=0, z=0)),
                covariance=np.zeros(36))
            odom = M["nav_msgs/msg/Odometry"](header=hdr, child_frame_id="base_link", pose=cov, twist=tw)
            w.write(co, ns, ts.serialize_cdr(odom, "nav_msgs/msg/Odometry"))
    for source in ("topic", "odometry"):
        scene = read_bag(out, BagOptions(pose_source=source), test_every=0)
        assert len(scene.train) == 4, scene.info
        for got, want in zip(scene.train, frames):
            np.testing.assert_allclose(got.cam_to_world, want.cam_to_world, atol=1e-6)


def test_frames_without_tf_are_dropped_and_counted(frames, tmp_path):
    """A dropout of odom -> base_link at frame 5 (a 0.133 s gap): with tf_max_gap 0.12 s (map -> odom comes at 10 Hz)
    those frames are dropped with the reason; with tf2's any-gap interpolation they are kept."""
    b = write_scene_bag(frames, tmp_path / "gaps", tf_missing=[5])
    scene = read_bag(b, BagOptions(tf_max_gap=0.12), test_every=0)
    assert len(scene.train) == N_FRAMES - 1 and scene.info["dropped"] == {"tf": 1}
    assert "gap of 0.133 s" in scene.info["dropped_examples"]["tf"]
    assert "camera_color_optical_frame" in scene.info["dropped_examples"]["tf"]
    assert len(read_bag(b, BagOptions(tf_max_gap=0.0), test_every=0).train) == N_FRAMES


# ------------------------------------------------------------------------------ bad input

def test_missing_and_truncated_bags(bag, tmp_path):
    with pytest.raises(SceneError, match="not a scene folder or bag"):
        read_scene(tmp_path)
    mcap = next(bag.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(SceneError, match=r"cut\.mcap: .*truncated"):
        read_bag(cut)
    junk = tmp_path / "junk.db3"
    junk.write_bytes(b"not a database" * 10)
    with pytest.raises(SceneError, match=r"junk\.db3"):
        read_bag(junk)


def test_wrong_topics_and_frames(bag, tmp_path):
    with pytest.raises(SceneError, match=r"colour topic '/nope' is not in the bag; its topics: .*/tf_static"):
        read_bag(bag, BagOptions(color_topic="/nope"))
    with pytest.raises(SceneError, match=r"depth topic '/tf' has type tf2_msgs/msg/TFMessage"):
        read_bag(bag, BagOptions(depth_topic="/tf"))
    with pytest.raises(SceneError, match=r"no usable frame.*tf x10.*\"base_footprint\" passed to lookup"):
        read_bag(bag, BagOptions(map_frame="base_footprint"))

    def wrong_frame(topic, msg):
        if topic in (COLOR_TOPIC, DEPTH_TOPIC, INFO_TOPIC):
            msg.header.frame_id = "camera_depth_optical_frame"
        return msg

    with pytest.raises(SceneError, match=r"camera_depth_optical_frame.*does not exist"):
        read_bag(rewrite(bag, tmp_path / "wrongframe", wrong_frame))
    with pytest.raises(ValueError, match="pose_source: expected 'tf', 'topic' or 'odometry', got 'gps'"):
        BagOptions(pose_source="gps")
    with pytest.raises(ValueError, match=r"tf_max_gap: expected greater than or equal to 0, got -1.*sync_slop: expected a "
                       "finite number, got nan"):
        BagOptions(tf_max_gap=-1, sync_slop=float("nan"))


def test_tf_loop_nan_transform_and_zero_focal_length(bag, tmp_path):
    def corrupt(topic, msg):
        if topic == "/tf" and msg.transforms[0].child_frame_id == "odom":
            sec = msg.transforms[0].header.stamp.sec + msg.transforms[0].header.stamp.nanosec * 1e-9
            if int(round(sec * 10)) % 3 == 0:   # a third of the map -> odom samples carry NaN
                msg.transforms[0].transform.translation.x = math.nan
        if topic == "/tf_static":   # and a loop: camera_color_optical_frame -> base_link
            loop = msg.transforms[0].__class__(header=msg.transforms[1].header, child_frame_id="base_link",
                                               transform=msg.transforms[1].transform)
            loop.header = msg.transforms[1].header.__class__(stamp=msg.transforms[1].header.stamp,
                                                             frame_id="camera_color_optical_frame")
            msg.transforms.append(loop)
        if topic == INFO_TOPIC and msg.header.stamp.nanosec % 3 == 0:
            msg.k = np.zeros(9)
        return msg

    scene = read_bag(rewrite(bag, tmp_path / "bad", corrupt), test_every=0)
    info = scene.info
    ex = info["tf_rejected_examples"]   # /tf_static comes first in the bag
    assert "'camera_color_optical_frame' <- 'base_link'" in ex[0] and "would close a loop" in ex[0]
    assert "NaN" in ex[1]
    assert info["tf_rejected"] == 1 + 3, info["tf_rejected"]   # the loop + a third of 9 map -> odom samples
    assert info["dropped"].get("camera_info", 0) >= 1
    assert "focal lengths must be > 0" in info["dropped_examples"]["camera_info"]
    assert len(scene.train) == N_FRAMES - info["dropped"].get("camera_info", 0) - info["dropped"].get("tf", 0)
    assert len(scene.train) > 0


def test_unknown_encoding_is_refused_with_the_supported_list(bag, tmp_path):
    def weird(topic, msg):
        if topic == COLOR_TOPIC:
            msg.format = "rgb8; theora"
        return msg

    with pytest.raises(SceneError, match=r"format 'rgb8; theora' is not supported for color; supported: jpeg or png"):
        read_bag(rewrite(bag, tmp_path / "weird", weird))


# ------------------------------------------------------------------------------ decoding

class Msg:
    """A duck-typed message (rosbags' and rclpy's share the field names)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def test_compressed_depth_16uc1_and_32fc1():
    rng = np.random.default_rng(0)
    d = rng.uniform(0.3, 4.0, (12, 9)).astype(np.float32)
    d[0, 0], d[1, 1] = 0, np.nan
    m = Msg(format="16UC1; compressedDepth png", data=np.frombuffer(ri.encode_compressed_depth(d), np.uint8))
    out = ri.decode_depth(m)
    want = np.where(np.isfinite(d), np.round(d * 1000) / 1000, 0)
    np.testing.assert_allclose(out, want, atol=1e-6)
    # 32FC1: image_transport's inverse-depth quantisation (depth_quantization 100, depth_max 10)
    qa = 100.0 * 101.0
    qb = 1.0 - qa / 10.0
    inv = np.where(d > 0, qa / np.nan_to_num(d, nan=1.0) + qb, 0)
    inv[1, 1] = 0
    ok, png = cv2.imencode(".png", inv.astype(np.uint16))
    m = Msg(format="32FC1; compressedDepth png", data=np.frombuffer(struct.pack("<iff", 1, qa, qb) + png.tobytes(),
                                                                        np.uint8))
    out = ri.decode_depth(m)
    valid = np.isfinite(d) & (d > 0)
    assert (out[~valid] == 0).all()
    np.testing.assert_allclose(out[valid], d[valid], rtol=2e-3)


@pytest.mark.parametrize("fmt, data, match", [
    ("16UC1; compressedDepth png", b"\x01\x00\x00\x00", "less than its 12-byte header"),
    ("16UC1; compressedDepth png", struct.pack("<iff", 1, 0, 0) + b"\x89PNG garbage", "cannot decode"),
    ("16UC1; compressedDepth rvl", struct.pack("<iff", 2, 0, 0) + b"x" * 20, "RVL"),
    ("8UC3; compressedDepth png", struct.pack("<iff", 1, 0, 0) + b"x" * 20, "'8UC3' is not supported"),
    ("16UC1", b"x" * 20, "not compressedDepth"),
])
def test_bad_compressed_depth(fmt, data, match):
    with pytest.raises(ri.ImageDecodeError, match=match):
        ri.compressed_depth_to_metres(Msg(format=fmt, data=np.frombuffer(data, np.uint8)))


def test_compressed_colour_jpeg_png_mono_and_errors():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (16, 24, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    np.testing.assert_array_equal(ri.decode_color(Msg(format="bgr8; png compressed bgr8", data=png.tobytes())), rgb)
    smooth = np.repeat(np.repeat(rgb[:2, :3], 8, 0), 8, 1)
    out = ri.decode_color(Msg(format="jpeg", data=ri.encode_jpeg(smooth, 95)))
    assert np.abs(out.astype(int) - smooth).mean() < 8   # chroma subsampling at the colour edges; a channel swap is ~100
    ok, grey = cv2.imencode(".png", rgb[..., 0])
    out = ri.decode_color(Msg(format="mono8; png compressed mono8", data=grey.tobytes()))
    assert out.shape == (16, 24, 3) and (out[..., 0] == rgb[..., 0]).all()
    with pytest.raises(ri.ImageDecodeError, match="cannot decode"):
        ri.decode_color(Msg(format="jpeg", data=ri.encode_jpeg(smooth)[:40]))
    with pytest.raises(ri.ImageDecodeError, match="is a depth image"):
        ri.decode_color(Msg(format="16UC1; compressedDepth png", data=b"x"))
    with pytest.raises(ri.ImageDecodeError, match="'h264' is not supported"):
        ri.decode_color(Msg(format="h264", data=b"x"))
    # raw mono8 colour
    raw = Msg(encoding="mono8", height=2, width=3, step=3, is_bigendian=0, data=np.arange(6, dtype=np.uint8))
    np.testing.assert_array_equal(ri.decode_color(raw)[..., 2], np.arange(6).reshape(2, 3))
    with pytest.raises(ri.ImageDecodeError, match="'yuv422' is not supported"):
        ri.decode_color(Msg(encoding="yuv422", height=2, width=3, step=6, is_bigendian=0, data=b"x" * 12))


# ------------------------------------------------------------------------------ rg map BAG

# `python -c NO_ROS_CLI ARGS...`: the rg CLI in a process where every ROS 2 Python package fails to
# import, so `rg map BAG` is shown to need no ROS install (rosbags parses the bag in pure Python).
NO_ROS_CLI = """
import importlib.abc, sys
class NoRos(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        top = name.split('.')[0]
        if top.startswith(('rclpy', 'rosidl', 'rmw', 'rpyutils', 'rg_interfaces')) or top.endswith(('_msgs', '_srvs')):
            raise ImportError('ROS is not installed in this test process: ' + name)
sys.meta_path.insert(0, NoRos())
from rg_core.cli import main
code = main(sys.argv[1:])
assert not [m for m in sys.modules if m.startswith('rclpy') or m.endswith('_msgs')]
sys.exit(code)
"""


def test_rg_map_bag_matches_the_folder(frames, tmp_path):
    """`rg map` on a lossless bag (raw bgr8 / 16UC1 images) and on the same frames as a folder: the
    same keyframes and test views, and test PSNR within 0.05 dB (160 px, short budgets;
    benchmarks/bench_bag.py measures the full scene). The maps differ only by the poses' float64
    round trip through four TF links (1e-12 m); measured, 2026-12-01: 0.000-0.004 dB over one and two
    threads and torch's default, AVX2 and AVX-512 kernels. JPEG colour (the default bag) changes the
    images themselves (0.24 dB here), so it is not what this compares; test_bag_reads_back_the_scene
    bounds its error."""
    import os
    import subprocess
    import sys

    def rg(*args):
        # headless: the process cannot import ROS at all (rclpy, any *_msgs / *_srvs / rosidl / rmw module)
        r = subprocess.run([sys.executable, "-c", NO_ROS_CLI, *args], capture_output=True, text=True, timeout=600)
        return r.returncode, json.loads(r.stdout)

    folder = tmp_path / "folder"
    folder.mkdir()
    src = need_rgbd("box_toys_50")
    os.symlink(next(src.glob("*.K.txt")), folder / "intrinsics.K.txt")
    for f in frames:
        for p in src.glob(f"frame-{f.index:06d}.*"):
            os.symlink(p, folder / p.name)
    # a folder's frames are stamped by index (1 s apart) and keyframe selection reads stamps
    # (map.kf_min_interval): the bag carries the same timing so both maps see the same keyframes
    b = write_scene_bag(frames, tmp_path / "bag", period=1.0, raw=True)
    cfg = tmp_path / "small.yaml"
    cfg.write_text("map:\n  width: 160\n  iters_per_keyframe: 5\n  final_iters: 30\n")
    out = {}
    for name, scene in (("folder", folder), ("bag", b)):
        code, out[name] = rg("--config", str(cfg), "map", str(scene), "--out", str(tmp_path / f"{name}.rgmap"),
                             "--json", "--quiet")
        assert code == 0, out[name]
    assert out["bag"]["bag"]["frames"] == N_FRAMES and out["bag"]["test_frames"] == out["folder"]["test_frames"] == 2
    assert out["bag"]["keyframes"] == out["folder"]["keyframes"], (out["bag"], out["folder"])
    diff = out["bag"]["test"]["psnr"] - out["folder"]["test"]["psnr"]
    print(f"test PSNR: bag {out['bag']['test']['psnr']:.3f}, folder {out['folder']['test']['psnr']:.3f} dB")
    assert abs(diff) <= 0.05, (out["bag"]["test"], out["folder"]["test"])
    # options reach the reader; a bad one is a clear error
    code, res = rg("map", str(b), "--out", str(tmp_path / "x.rgmap"), "--pose-source", "topic", "--json", "--quiet")
    assert code == 2 and "pose_source topic: no geometry_msgs/msg/PoseStamped topic" in res["error"]
