"""Message <-> numpy conversions of rg_ros (images, intrinsics, poses, PointCloud2, stamps)."""
from __future__ import annotations

import math
import os
import random
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # never multicast onto the network
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("ROS_LOG_DIR", str(Path(__file__).resolve().parents[1] / ".ros_log"))

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from geometry_msgs.msg import Pose, PoseStamped  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField  # noqa: E402

from rg_core.geometry.conventions import PoseError, look_at  # noqa: E402
from rg_core.geometry.rotations import quat_to_rot  # noqa: E402
from rg_core.io.ros_images import COLOR_ENCODINGS, camera_info_K  # noqa: E402
from rg_ros import convert as cv  # noqa: E402
from rg_ros.pointcloud import from_pointcloud2, to_pointcloud2  # noqa: E402

RNG = np.random.default_rng(0)


def make_image(arr: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False,
               drop_last_pad: bool = False) -> Image:
    """Build an Image by hand (independent of rg_ros), with `pad` bytes after each row."""
    arr = np.asarray(arr)
    h, w = arr.shape[:2]
    typed = arr.astype(arr.dtype.newbyteorder(">" if bigendian else "<"))
    rows = typed.reshape(h, -1).view(np.uint8).reshape(h, -1)
    padded = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1).reshape(-1)
    data = padded[:-pad] if (drop_last_pad and pad) else padded
    return Image(height=h, width=w, encoding=encoding, is_bigendian=bigendian, step=rows.shape[1] + pad,
                 data=data.tobytes())


# ------------------------------------------------------------------------------------ images

RGB = RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8)
ALPHA = RNG.integers(0, 256, (5, 7, 1), dtype=np.uint8)
COLOUR_LAYOUTS = {"rgb8": RGB, "bgr8": RGB[..., ::-1], "rgba8": np.concatenate([RGB, ALPHA], -1),
                  "bgra8": np.concatenate([RGB[..., ::-1], ALPHA], -1)}


@pytest.mark.parametrize("pad", [0, 3, 8])
@pytest.mark.parametrize("encoding", list(COLOUR_LAYOUTS))
def test_colour_images_decode_to_rgb(encoding, pad):
    out = cv.image_to_rgb(make_image(COLOUR_LAYOUTS[encoding], encoding, pad=pad))
    assert out.dtype == np.uint8 and out.shape == (5, 7, 3) and out.flags.c_contiguous
    np.testing.assert_array_equal(out, RGB)


@pytest.mark.parametrize("encoding", list(cv.ENCODINGS))
def test_to_image_round_trips_every_encoding(encoding):
    dtype, ch = cv.ENCODINGS[encoding]
    shape = (6, 4) if ch == 1 else (6, 4, ch)
    arr = (RNG.random(shape) * 5).astype(dtype) if dtype == np.float32 else RNG.integers(1, 200, shape).astype(dtype)
    msg = cv.to_image(arr, encoding, frame_id="cam", stamp=3.25)
    assert msg.step == 4 * ch * np.dtype(dtype).itemsize and len(msg.data) == msg.step * 6
    assert msg.header.frame_id == "cam" and cv.from_time(msg.header.stamp) == 3.25
    msg = deserialize_message(serialize_message(msg), Image)
    if encoding in COLOR_ENCODINGS:
        want = arr[..., :3][..., ::-1] if encoding.startswith("bgr") else arr[..., :3]
        np.testing.assert_array_equal(cv.image_to_rgb(msg), want)
    elif encoding == "16UC1":
        np.testing.assert_allclose(cv.image_to_depth(msg), arr.astype(np.float32) / 1000, rtol=1e-6)
    elif encoding == "32FC1":
        np.testing.assert_array_equal(cv.image_to_depth(msg), arr)
    else:
        np.testing.assert_array_equal(cv.image_to_mask(msg), arr)


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("pad", [0, 2, 5])
def test_depth_16uc1_is_millimetres(pad, bigendian):
    mm = np.array([[0, 1, 1000], [65535, 250, 0]], np.uint16)
    out = cv.image_to_depth(make_image(mm, "16UC1", pad=pad, bigendian=bigendian))
    assert out.dtype == np.float32 and out.shape == (2, 3)
    np.testing.assert_allclose(out, [[0, 0.001, 1.0], [65.535, 0.25, 0]], rtol=1e-6)


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("pad", [0, 4, 1])
def test_depth_32fc1_invalid_values_become_zero(pad, bigendian):
    m = np.array([[1.5, np.nan, np.inf], [-np.inf, -2.0, 0.0], [0.25, 7.0, 1e-3]], np.float32)
    out = cv.image_to_depth(make_image(m, "32FC1", pad=pad, bigendian=bigendian))
    np.testing.assert_array_equal(out, np.array([[1.5, 0, 0], [0, 0, 0], [0.25, 7.0, 1e-3]], np.float32))


def test_last_row_padding_may_be_missing():
    out = cv.image_to_rgb(make_image(RGB, "rgb8", pad=5, drop_last_pad=True))
    np.testing.assert_array_equal(out, RGB)


def test_mask_and_depth_helpers():
    mask = RNG.random((3, 4)) > 0.5
    msg = cv.mask_to_image(mask)
    assert msg.encoding == "mono8"
    np.testing.assert_array_equal(cv.image_to_mask(msg), mask.astype(np.uint8) * 255)
    d = RNG.random((3, 4)).astype(np.float32)
    assert cv.depth_to_image(d).encoding == "32FC1"
    np.testing.assert_array_equal(cv.image_to_depth(cv.depth_to_image(d)), d)


@pytest.mark.parametrize("encoding", ["yuv422", "mono16", "8UC3", "", "rgb16"])
def test_unsupported_encodings_name_encoding_and_alternatives(encoding):
    msg = Image(height=2, width=2, encoding=encoding, step=6, data=bytes(12))
    with pytest.raises(ValueError, match=f"'{encoding}'.*supported: rgb8, bgr8, rgba8, bgra8"):
        cv.image_to_rgb(msg)
    with pytest.raises(ValueError, match="supported: 16UC1, 32FC1"):
        cv.image_to_depth(msg)


def test_colour_and_depth_decoders_refuse_each_other():
    with pytest.raises(ValueError, match="'32FC1'"):
        cv.image_to_rgb(cv.depth_to_image(np.ones((2, 2), np.float32)))
    with pytest.raises(ValueError, match="'rgb8'"):
        cv.image_to_depth(cv.rgb_to_image(RGB))


def test_bad_image_sizes():
    good = make_image(RGB, "rgb8")
    short = Image(height=5, width=7, encoding="rgb8", step=21, data=bytes(good.data)[:-1])
    with pytest.raises(ValueError, match="needs 105"):
        cv.image_to_rgb(short)
    with pytest.raises(ValueError, match="step 20 < width"):
        cv.image_to_rgb(Image(height=5, width=7, encoding="rgb8", step=20, data=bytes(200)))
    with pytest.raises(ValueError, match="empty"):
        cv.image_to_rgb(Image(height=0, width=7, encoding="rgb8", step=21, data=b""))
    with pytest.raises(ValueError, match="dtype"):
        cv.to_image(RGB.astype(np.float32), "rgb8")
    with pytest.raises(ValueError, match="shape"):
        cv.to_image(RGB[..., :2], "rgb8")
    with pytest.raises(ValueError, match="'nv12'"):
        cv.to_image(RGB, "nv12")


# -------------------------------------------------------------------------------- intrinsics

def camera_info(k, width=640, height=480) -> CameraInfo:
    return CameraInfo(width=width, height=height, k=[float(v) for v in k])


def test_camera_info_to_K():
    K, size = camera_info_K(camera_info([525, 0, 319.5, 0, 526, 239.5, 0, 0, 1]))
    np.testing.assert_array_equal(K, [[525, 0, 319.5], [0, 526, 239.5], [0, 0, 1]])
    assert size == (640, 480) and K.dtype == np.float64


@pytest.mark.parametrize("k, size, match", [
    ([0] * 9, (640, 480), "focal lengths must be > 0"),
    ([525, 0, 320, 0, 0, 240, 0, 0, 1], (640, 480), "focal lengths"),
    ([-525, 0, 320, 0, 525, 240, 0, 0, 1], (640, 480), "focal lengths"),
    ([525, 0, 320, 0, 525, 240, 0, 0, 1], (0, 480), "empty"),
    ([525, 0, math.nan, 0, 525, 240, 0, 0, 1], (640, 480), "NaN"),
    ([525, 0, 320, 0, 525, 240, 0, 0, 2], (640, 480), "pinhole"),
])
def test_bad_camera_info(k, size, match):
    with pytest.raises(ValueError, match=match):
        camera_info_K(camera_info(k, *size))


# ------------------------------------------------------------------------------------- poses

def random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return quat_to_rot(q / np.linalg.norm(q))


@pytest.mark.parametrize("seed", range(20))
def test_pose_round_trip(seed):
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = random_rotation(rng), rng.normal(size=3) * 10
    pose = cv.matrix_to_pose(T)
    q = [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and pose.orientation.w >= 0
    np.testing.assert_allclose(cv.pose_to_matrix(pose), T, atol=1e-12)
    np.testing.assert_allclose(cv.pose_to_matrix(PoseStamped(pose=pose)), T, atol=1e-12)


@pytest.mark.parametrize("R", [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)])
def test_half_turns_and_identity(R):
    T = np.eye(4)
    T[:3, :3] = R
    np.testing.assert_allclose(cv.pose_to_matrix(cv.matrix_to_pose(T)), T, atol=1e-12)


def test_pose_of_a_look_at_camera_passes_through():
    T = look_at([1.0, -2.0, 1.5], [0.0, 0.0, 0.5])   # OpenCV axes, as a ROS optical frame
    np.testing.assert_allclose(cv.pose_to_matrix(cv.matrix_to_pose(T)), T, atol=1e-12)


def test_slightly_unnormalised_quaternion_is_normalised():
    pose = Pose()
    pose.orientation.w, pose.orientation.z = 0.705, 0.705   # norm 0.997: rounding, not a broken pose
    R = cv.pose_to_matrix(pose)[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


@pytest.mark.parametrize("q, pos, match", [
    ((0, 0, 0, 0), (0, 0, 0), "norm is 0"),
    ((0, 0, 0, 2), (0, 0, 0), "norm is 2"),
    ((0.5, 0, 0, 0.5), (0, 0, 0), "norm"),
    ((math.nan, 0, 0, 1), (0, 0, 0), "NaN"),
    ((0, 0, 0, 1), (0, math.inf, 0), "position"),
])
def test_bad_poses(q, pos, match):
    pose = Pose()
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = map(float, q)
    pose.position.x, pose.position.y, pose.position.z = map(float, pos)
    with pytest.raises(PoseError, match=match):
        cv.pose_to_matrix(pose)
    with pytest.raises(ValueError):   # PoseError is a ValueError
        cv.pose_to_matrix(pose)


def test_matrix_to_pose_rejects_non_rigid():
    with pytest.raises(PoseError, match="reflection"):
        cv.matrix_to_pose(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(PoseError, match="orthonormal"):
        cv.matrix_to_pose(np.diag([2.0, 1.0, 1.0, 1.0]))
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(PoseError, match="NaN"):
        cv.matrix_to_pose(T)


# ------------------------------------------------------------------------------------ stamps

def test_stamps():
    t = cv.to_time(1.5)
    assert (t.sec, t.nanosec) == (1, 500_000_000)
    t = cv.to_time(0.9999999999)
    assert (t.sec, t.nanosec) == (1, 0)
    assert cv.from_time(cv.to_time(1_700_000_000.123456789)) == pytest.approx(1_700_000_000.123456789, abs=1e-6)
    assert cv.header("map", 2.0).stamp.sec == 2 and cv.header().frame_id == ""
    for bad in (-1.0, math.nan, math.inf, 2.0**31):
        with pytest.raises(ValueError, match="stamp"):
            cv.to_time(bad)


def test_parse_mode():
    from rg_core.perception.query import parse_mode

    assert parse_mode("") == "auto" and parse_mode(" Implicit ") == "implicit"
    assert parse_mode("explicit") == "explicit"
    with pytest.raises(ValueError, match="'fuzzy'"):
        parse_mode("fuzzy")


# -------------------------------------------------------------------------------- PointCloud2

def test_pointcloud_round_trip_with_colour():
    pts = RNG.normal(size=(100, 3)).astype(np.float32)
    cols = RNG.integers(0, 256, (100, 3), dtype=np.uint8)
    msg = to_pointcloud2(pts, cols, "map", cv.to_time(4.0))
    assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb"]
    assert msg.fields[3].datatype == PointField.FLOAT32 and msg.point_step == 16 and msg.row_step == 1600
    assert msg.height == 1 and msg.width == 100 and msg.is_dense and msg.header.frame_id == "map"
    p, c = from_pointcloud2(msg)
    np.testing.assert_array_equal(p, pts)
    np.testing.assert_array_equal(c, cols)


def test_packed_rgb_is_what_rviz_reads():
    msg = to_pointcloud2(np.zeros((3, 3), np.float32), np.array([[255, 0, 0], [0, 255, 0], [1, 2, 3]], np.uint8))
    bits = np.frombuffer(bytes(msg.data), np.uint32).reshape(3, 4)[:, 3]
    assert bits.tolist() == [0xFF0000, 0x00FF00, 0x010203]


def test_pointcloud_without_colour_and_empty():
    pts = RNG.normal(size=(10, 3)).astype(np.float32)
    msg = to_pointcloud2(pts)
    assert msg.point_step == 12 and [f.name for f in msg.fields] == ["x", "y", "z"]
    p, c = from_pointcloud2(msg)
    np.testing.assert_array_equal(p, pts)
    assert c is None
    p, c = from_pointcloud2(to_pointcloud2(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)))
    assert p.shape == (0, 3) and c.shape == (0, 3)
    p, c = from_pointcloud2(to_pointcloud2(np.zeros((0, 3))))
    assert p.shape == (0, 3) and p.dtype == np.float32 and c is None
    p, c = from_pointcloud2(PointCloud2())   # default-constructed: no fields, no points
    assert p.shape == (0, 3) and c is None


def test_nan_points_make_cloud_not_dense():
    pts = np.array([[0, 0, 1], [np.nan, 0, 0]], np.float32)
    msg = to_pointcloud2(pts)
    assert not msg.is_dense
    np.testing.assert_array_equal(from_pointcloud2(msg)[0], pts)


def test_pointcloud_serialization_round_trip():
    pts = RNG.normal(size=(1000, 3)).astype(np.float32)
    cols = RNG.integers(0, 256, (1000, 3), dtype=np.uint8)
    wire = serialize_message(to_pointcloud2(pts, cols, "map", cv.to_time(12.5)))
    msg = deserialize_message(wire, PointCloud2)
    assert msg.header.frame_id == "map" and cv.from_time(msg.header.stamp) == 12.5
    p, c = from_pointcloud2(msg)
    np.testing.assert_array_equal(p, pts)
    np.testing.assert_array_equal(c, cols)


@pytest.mark.parametrize("bigendian", [False, True])
def test_foreign_layout_float64_padding_rows_and_endianness(bigendian):
    """An organised 2x3 cloud: float64 xyz at odd offsets, an intensity field, uint32 rgba, row padding."""
    h, w, step, row_pad = 2, 3, 40, 7
    o = ">" if bigendian else "<"
    dt = np.dtype({"names": ["intensity", "x", "y", "z", "rgba"],
                   "formats": [o + "f4", o + "f8", o + "f8", o + "f8", o + "u4"],
                   "offsets": [0, 4, 12, 20, 28], "itemsize": step})
    rec = np.zeros(h * w, dt)
    pts = RNG.normal(size=(h * w, 3))
    cols = RNG.integers(0, 256, (h * w, 3), dtype=np.uint8)
    rec["x"], rec["y"], rec["z"] = pts.T
    rec["rgba"] = (0xFF << 24) | (cols[:, 0].astype(np.uint32) << 16) | (cols[:, 1].astype(np.uint32) << 8) | cols[:, 2]
    rows = rec.view(np.uint8).reshape(h, w * step)
    data = np.concatenate([rows, np.full((h, row_pad), 0xEE, np.uint8)], 1).tobytes()
    fields = [PointField(name="intensity", offset=0, datatype=PointField.FLOAT32, count=1),
              PointField(name="x", offset=4, datatype=PointField.FLOAT64, count=1),
              PointField(name="y", offset=12, datatype=PointField.FLOAT64, count=1),
              PointField(name="z", offset=20, datatype=PointField.FLOAT64, count=1),
              PointField(name="rgba", offset=28, datatype=PointField.UINT32, count=1)]
    msg = PointCloud2(height=h, width=w, fields=fields, is_bigendian=bigendian, point_step=step,
                      row_step=w * step + row_pad, data=data)
    p, c = from_pointcloud2(deserialize_message(serialize_message(msg), PointCloud2))
    np.testing.assert_allclose(p, pts.astype(np.float32))
    np.testing.assert_array_equal(c, cols)


def test_separate_uint8_colour_channels():
    dt = np.dtype({"names": ["x", "y", "z", "b", "g", "r"], "formats": ["<f4"] * 3 + ["u1"] * 3,
                   "offsets": [0, 4, 8, 12, 13, 14], "itemsize": 16})
    rec = np.zeros(4, dt)
    rec["x"] = [1, 2, 3, 4]
    rec["r"], rec["g"], rec["b"] = [10, 20, 30, 40], [1, 2, 3, 4], [5, 6, 7, 8]
    fields = [PointField(name=n, offset=dt.fields[n][1], datatype=PointField.FLOAT32 if n in "xyz" else PointField.UINT8,
                         count=1) for n in dt.names]
    p, c = from_pointcloud2(PointCloud2(height=1, width=4, fields=fields, point_step=16, row_step=64,
                                        data=rec.tobytes()))
    np.testing.assert_array_equal(p[:, 0], [1, 2, 3, 4])
    np.testing.assert_array_equal(c, [[10, 1, 5], [20, 2, 6], [30, 3, 7], [40, 4, 8]])


def _xyz_fields(datatype=PointField.FLOAT32, count=1, z_offset=8):
    return [PointField(name="x", offset=0, datatype=datatype, count=count),
            PointField(name="y", offset=4, datatype=datatype, count=count),
            PointField(name="z", offset=z_offset, datatype=datatype, count=count)]


@pytest.mark.parametrize("kwargs, match", [
    (dict(fields=_xyz_fields()[:2]), "no 'z' field"),
    (dict(fields=_xyz_fields(count=2)), "count 2"),
    (dict(fields=_xyz_fields(datatype=PointField.INT16)), "datatype i2 not supported"),
    (dict(fields=_xyz_fields(datatype=42)), "unknown datatype 42"),
    (dict(fields=_xyz_fields(z_offset=10)), "past point_step 12"),
    (dict(fields=_xyz_fields(), row_step=20), "row_step 20 <"),
    (dict(fields=_xyz_fields(), data=bytes(23)), "has 23 bytes"),
    (dict(fields=_xyz_fields() + [PointField(name="rgb", offset=8, datatype=PointField.UINT16, count=1)],
          point_step=12), "packed colour must be 4 bytes"),
])
def test_pointcloud_bad_layouts(kwargs, match):
    msg = PointCloud2(height=1, width=2, point_step=12, row_step=24, data=bytes(24))
    for k, v in kwargs.items():
        setattr(msg, k, v)
    with pytest.raises(ValueError, match=match):
        from_pointcloud2(msg)


def test_to_pointcloud2_checks_shapes():
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        to_pointcloud2(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="colors"):
        to_pointcloud2(np.zeros((4, 3)), np.zeros((3, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        to_pointcloud2(np.zeros((4, 3)), np.zeros((4, 3), np.float32))
