"""Write a scene as a RealSense-style rosbag2 (test data and a reference for what `rg map BAG` reads).

Topics (realsense2_camera names, image_transport suffixes):
  /camera/camera/color/image_raw/compressed                  CompressedImage, 'rgb8; jpeg compressed bgr8'
  /camera/camera/aligned_depth_to_color/image_raw/compressedDepth   CompressedImage, '16UC1; compressedDepth png'
  /camera/camera/color/camera_info                           CameraInfo
  /tf         map -> odom (10 Hz, slow linear drift + yaw) and odom -> base_link (at every frame)
  /tf_static  base_link -> camera_link -> camera_color_optical_frame (the REP 103 optical rotation)

The scene's camera poses are split over that tree so that a tf2-style lookup of
map <- camera_color_optical_frame at a frame's stamp gives the scene pose back exactly: map -> odom
moves linearly in translation and yaw, which linear + slerp interpolation reproduces at any stamp.
`tf_missing` lists frame positions whose odom -> base_link sample is left out (a TF dropout).
Written with rosbags' Writer (mcap or sqlite3); no ROS install needed.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..geometry.conventions import BODY_FROM_OPTICAL
from ..geometry.rotations import rot_to_quat
from . import ros_images

COLOR_TOPIC = "/camera/camera/color/image_raw/compressed"
DEPTH_TOPIC = "/camera/camera/aligned_depth_to_color/image_raw/compressedDepth"
INFO_TOPIC = "/camera/camera/color/camera_info"
OPTICAL_FRAME = "camera_color_optical_frame"
# base_link -> camera_link (a camera 20 cm ahead, 30 cm up, pitched down 10 degrees)
BASE_FROM_CAMLINK_T = np.array([0.2, 0.0, 0.3])
BASE_FROM_CAMLINK_PITCH = math.radians(10.0)


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def map_from_odom(t: float, t0: float) -> np.ndarray:
    """The drifting map <- odom correction: 2 cm/s in x, -1 cm/s in y, 0.5 deg/s of yaw."""
    dt = t - t0
    return _T(_rot_z(math.radians(0.5) * dt), [0.02 * dt, -0.01 * dt, 0.0])


def base_from_optical() -> np.ndarray:
    camlink = _T(_rot_y(BASE_FROM_CAMLINK_PITCH), BASE_FROM_CAMLINK_T)
    return camlink @ BODY_FROM_OPTICAL   # camera_link (x fwd, z up) <- optical (z fwd, y down)


def write_scene_bag(frames, out: str | Path, stamp0: float = 1_700_000_000.0, period: float = 1.0 / 15.0,
                    jpeg_quality: int = 95, tf_missing=(), storage: str = "mcap", map_frame: str = "map",
                    raw: bool = False) -> Path:
    """Write posed RGB-D `frames` (rg_core Frame) as a rosbag2 folder `out`; returns `out`.
    Frame i is stamped stamp0 + i * period. raw=True: uncompressed sensor_msgs/Image (bgr8 colour,
    16UC1 depth) on the topics without the image_transport suffix."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_KILTED)
    M = ts.types
    Time, Header = M["builtin_interfaces/msg/Time"], M["std_msgs/msg/Header"]
    Vec, Quat = M["geometry_msgs/msg/Vector3"], M["geometry_msgs/msg/Quaternion"]
    Transform, TS = M["geometry_msgs/msg/Transform"], M["geometry_msgs/msg/TransformStamped"]
    TFMessage, Compressed = M["tf2_msgs/msg/TFMessage"], M["sensor_msgs/msg/CompressedImage"]
    CameraInfo, ROI = M["sensor_msgs/msg/CameraInfo"], M["sensor_msgs/msg/RegionOfInterest"]
    RawImage = M["sensor_msgs/msg/Image"]

    def stamp(t: float):
        sec, ns = divmod(int(round(t * 1e9)), 1_000_000_000)
        return Time(sec=sec, nanosec=ns)

    def hdr(frame_id: str, t: float):
        return Header(stamp=stamp(t), frame_id=frame_id)

    def tstamped(parent: str, child: str, t: float, T: np.ndarray):
        x, y, z, w = rot_to_quat(T[:3, :3])
        return TS(header=hdr(parent, t), child_frame_id=child,
                  transform=Transform(translation=Vec(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                                      rotation=Quat(x=float(x), y=float(y), z=float(z), w=float(w))))

    frames = list(frames)
    if not frames:
        raise ValueError("write_scene_bag: no frames")
    out = Path(out)
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    t_end = stamp0 + (len(frames) - 1) * period
    T_bo = base_from_optical()
    T_bc = _T(_rot_y(BASE_FROM_CAMLINK_PITCH), BASE_FROM_CAMLINK_T)
    T_co = BODY_FROM_OPTICAL
    latched = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, QosTime(0, 0),
                  QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)
    msgs: list[tuple[float, str, object, str]] = []   # (log time, topic, message, type)
    msgs.append((stamp0 - 0.5, "/tf_static", TFMessage(transforms=[
        tstamped("base_link", "camera_link", stamp0, T_bc),
        tstamped("camera_link", OPTICAL_FRAME, stamp0, T_co)]), "tf2_msgs/msg/TFMessage"))
    n_mo = int(math.ceil((t_end - stamp0 + 0.2) / 0.1)) + 1
    for k in range(n_mo):   # 10 Hz from 0.1 s before the first frame to past the last one
        t = stamp0 - 0.1 + 0.1 * k
        msgs.append((t, "/tf", TFMessage(transforms=[tstamped(map_frame, "odom", t, map_from_odom(t, stamp0))]),
                     "tf2_msgs/msg/TFMessage"))
    missing = set(int(i) for i in tf_missing)
    for i, f in enumerate(frames):
        t = stamp0 + i * period
        c2w = np.asarray(f.cam_to_world, np.float64)
        if i not in missing:
            T_ob = np.linalg.inv(map_from_odom(t, stamp0)) @ c2w @ np.linalg.inv(T_bo)
            msgs.append((t, "/tf", TFMessage(transforms=[tstamped("odom", "base_link", t, T_ob)]),
                         "tf2_msgs/msg/TFMessage"))
        rgb, depth = f.load_rgb(), f.load_depth()
        h, w = rgb.shape[:2]
        K = np.asarray(f.intrinsics.K, np.float64)
        log_t = t + 0.005   # images arrive a little after their stamp
        if raw:
            bgr = np.ascontiguousarray(rgb[..., ::-1])
            mm = np.where(np.isfinite(depth) & (depth > 0), np.rint(depth * 1000.0), 0).clip(0, 65535).astype("<u2")
            msgs.append((log_t, COLOR_TOPIC.rsplit("/", 1)[0], RawImage(
                header=hdr(OPTICAL_FRAME, t), height=h, width=w, encoding="bgr8", is_bigendian=0, step=w * 3,
                data=bgr.reshape(-1)), "sensor_msgs/msg/Image"))
            msgs.append((log_t, DEPTH_TOPIC.rsplit("/", 1)[0], RawImage(
                header=hdr(OPTICAL_FRAME, t), height=h, width=w, encoding="16UC1", is_bigendian=0, step=w * 2,
                data=mm.view(np.uint8).reshape(-1)), "sensor_msgs/msg/Image"))
        else:
            msgs.append((log_t, COLOR_TOPIC, Compressed(
                header=hdr(OPTICAL_FRAME, t), format="rgb8; jpeg compressed bgr8",
                data=np.frombuffer(ros_images.encode_jpeg(rgb, jpeg_quality), np.uint8)), "sensor_msgs/msg/CompressedImage"))
            msgs.append((log_t, DEPTH_TOPIC, Compressed(
                header=hdr(OPTICAL_FRAME, t), format="16UC1; compressedDepth png",
                data=np.frombuffer(ros_images.encode_compressed_depth(depth), np.uint8)), "sensor_msgs/msg/CompressedImage"))
        P = np.hstack([K, np.zeros((3, 1))])
        msgs.append((log_t, INFO_TOPIC, CameraInfo(
            header=hdr(OPTICAL_FRAME, t), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5),
            k=K.reshape(-1), r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0,
            roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)), "sensor_msgs/msg/CameraInfo"))
    msgs.sort(key=lambda m: m[0])
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        conns = {}
        for _, topic, _, typ in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, typ, typestore=ts,
                                                     offered_qos_profiles=[latched] if topic == "/tf_static" else ())
        for t, topic, msg, typ in msgs:
            writer.write(conns[topic], int(round(t * 1e9)), ts.serialize_cdr(msg, typ))
    return out
