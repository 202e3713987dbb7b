"""Decoding (and encoding) of ROS image messages, and CameraInfo -> K, with numpy and OpenCV, no ROS
import (cv_bridge is not on PyPI). Duck-typed: works on rclpy messages and on rosbags' deserialised messages alike
(they share field names).

- sensor_msgs/Image: rgb8, bgr8, rgba8, bgra8, mono8 colour; 16UC1 (millimetres) and 32FC1
  (metres) depth; row padding (`step`) and big-endian data honoured.
- sensor_msgs/CompressedImage: jpeg/png colour (`format` "jpeg", "rgb8; jpeg compressed bgr8", ...)
  and image_transport's `compressedDepth`: `format` "16UC1; compressedDepth png" (or "32FC1; ...")
  and `data` = a 12-byte ConfigHeader (int32 compression format, float32 depthQuantA, depthQuantB)
  followed by a 16-bit PNG: raw millimetres for 16UC1, quantised inverse depth for 32FC1.
"""
from __future__ import annotations

import struct

import numpy as np

# encoding -> (numpy dtype, channels)
ENCODINGS = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
             "mono8": (np.uint8, 1), "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}
COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
DEPTH_ENCODINGS = ("16UC1", "32FC1")   # millimetres, metres
COMPRESSED_DEPTH_HEADER = 12           # sizeof(ConfigHeader) in compressed_depth_image_transport
_CD_INV_DEPTH, _CD_PNG, _CD_RVL = 0, 1, 2   # its compressionFormat enum


class ImageDecodeError(ValueError):
    """An image message could not be decoded; the message says what was wrong and what is supported."""


def _unsupported(encoding: str, allowed) -> ImageDecodeError:
    return ImageDecodeError(f"Image encoding '{encoding}' is not supported here; supported: {', '.join(allowed)}")


def image_array(msg, allowed) -> np.ndarray:
    """Image -> native-endian array [H, W, C] (a copy), honouring step padding and is_bigendian."""
    if msg.encoding not in allowed:
        raise _unsupported(msg.encoding, allowed)
    dtype, ch = ENCODINGS[msg.encoding]
    h, w = int(msg.height), int(msg.width)
    if h == 0 or w == 0:
        raise ImageDecodeError(f"Image is empty ({w}x{h})")
    item = np.dtype(dtype).itemsize
    row_bytes = w * ch * item
    if msg.step < row_bytes:
        raise ImageDecodeError(f"Image step {msg.step} < width * channels * bytes = {row_bytes} ({msg.encoding})")
    raw = np.frombuffer(_bytes(msg.data), dtype=np.uint8)
    need = (h - 1) * msg.step + row_bytes   # the last row's padding may be missing
    if raw.size < need:
        raise ImageDecodeError(f"Image data has {raw.size} bytes, {w}x{h} {msg.encoding} with step {msg.step} "
                               f"needs {need}")
    rows = np.lib.stride_tricks.as_strided(raw, shape=(h, row_bytes), strides=(msg.step, 1))   # [H, row_bytes]
    typed = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<") if item > 1 else np.dtype(dtype)
    arr = np.ascontiguousarray(rows).view(typed).reshape(h, w, ch)
    return arr.astype(np.dtype(dtype).newbyteorder("="), copy=True)


def _bytes(data) -> bytes | np.ndarray:
    if isinstance(data, (bytes, bytearray, memoryview, np.ndarray)):
        return data
    return bytes(data)   # array.array('B') / list from rclpy


def raw_to_rgb(msg, allow_mono: bool = True) -> np.ndarray:
    """Colour Image -> uint8 [H, W, 3] RGB (alpha dropped; mono8 repeated into three channels)."""
    allowed = COLOR_ENCODINGS + (("mono8",) if allow_mono else ())
    arr = image_array(msg, allowed)
    if msg.encoding == "mono8":
        return np.ascontiguousarray(np.repeat(arr, 3, axis=2))
    if msg.encoding.startswith("bgr"):
        arr = arr[..., 2::-1]
    return np.ascontiguousarray(arr[..., :3])


def depth_to_metres(arr: np.ndarray, encoding: str) -> np.ndarray:
    """uint16 millimetres or float32 metres [H, W] -> float32 metres; zero, NaN, inf and negative -> 0."""
    depth = arr.astype(np.float32) * np.float32(0.001) if encoding == "16UC1" else arr.astype(np.float32)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def raw_to_depth(msg) -> np.ndarray:
    """Depth Image (16UC1 mm or 32FC1 m) -> float32 [H, W] metres, 0 = invalid."""
    return depth_to_metres(image_array(msg, DEPTH_ENCODINGS)[..., 0], msg.encoding)


# ------------------------------------------------------------------------------ compressed

def _imdecode(buf: np.ndarray, flags: int, what: str) -> np.ndarray:
    import cv2

    if buf.size == 0:
        raise ImageDecodeError(f"{what}: no data")
    img = cv2.imdecode(buf, flags)
    if img is None:
        raise ImageDecodeError(f"{what}: OpenCV cannot decode the data ({buf.size} bytes; truncated or not an "
                               "image)")
    return img


def compressed_to_rgb(msg) -> np.ndarray:
    """CompressedImage (jpeg/png colour or grey) -> uint8 [H, W, 3] RGB."""
    import cv2

    fmt = (msg.format or "").strip()
    if "compresseddepth" in fmt.lower():
        raise ImageDecodeError(f"CompressedImage format '{fmt}' is a depth image, expected a colour one "
                               "(jpeg or png)")
    low = fmt.lower()
    if low and not any(k in low for k in ("jpeg", "jpg", "png")):
        raise ImageDecodeError(f"CompressedImage format '{fmt}' is not supported; supported: jpeg, png "
                               "(e.g. 'rgb8; jpeg compressed bgr8')")
    img = _imdecode(np.frombuffer(_bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED, f"CompressedImage ({fmt})")
    if img.dtype != np.uint8:
        raise ImageDecodeError(f"CompressedImage ({fmt}): decoded to {img.dtype}, a colour image must be 8-bit")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)   # OpenCV decodes to BGR whatever the publisher's order
    return np.ascontiguousarray(img)


def compressed_depth_to_metres(msg) -> np.ndarray:
    """compressedDepth CompressedImage -> float32 [H, W] metres, 0 = invalid."""
    import cv2

    fmt = (msg.format or "").strip()
    parts = [p.strip() for p in fmt.split(";")]
    if len(parts) < 2 or "compresseddepth" not in parts[1].lower():
        raise ImageDecodeError(f"CompressedImage format '{fmt}' is not compressedDepth (expected e.g. "
                               "'16UC1; compressedDepth png')")
    encoding = parts[0]
    if encoding not in DEPTH_ENCODINGS:
        raise _unsupported(encoding, DEPTH_ENCODINGS)
    if "rvl" in parts[1].lower():
        raise ImageDecodeError(f"CompressedImage format '{fmt}': RVL compressedDepth is not supported; "
                               "supported: png")
    data = np.frombuffer(_bytes(msg.data), np.uint8)
    if data.size <= COMPRESSED_DEPTH_HEADER:
        raise ImageDecodeError(f"compressedDepth image has {data.size} bytes, less than its "
                               f"{COMPRESSED_DEPTH_HEADER}-byte header plus a PNG")
    comp, qa, qb = struct.unpack("<iff", data[:COMPRESSED_DEPTH_HEADER].tobytes())
    if comp not in (_CD_INV_DEPTH, _CD_PNG):
        raise ImageDecodeError(f"compressedDepth header names compression format {comp}; supported: png (1)")
    img = _imdecode(data[COMPRESSED_DEPTH_HEADER:], cv2.IMREAD_UNCHANGED, f"compressedDepth ({fmt})")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise ImageDecodeError(f"compressedDepth ({fmt}): expected a single-channel 16-bit PNG, got {img.dtype} "
                               f"{img.shape}")
    if encoding == "16UC1":
        return depth_to_metres(img, "16UC1")
    if not (np.isfinite(qa) and np.isfinite(qb)) or qa == 0:
        raise ImageDecodeError(f"compressedDepth ({fmt}): bad inverse-depth quantisation A={qa}, B={qb}")
    inv = img.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(img > 0, np.float32(qa) / (inv - np.float32(qb)), 0.0).astype(np.float32)
    return depth_to_metres(depth, "32FC1")


def decode_color(msg) -> np.ndarray:
    """Image or CompressedImage (told apart by the `format` field) -> uint8 [H, W, 3] RGB."""
    return compressed_to_rgb(msg) if hasattr(msg, "format") else raw_to_rgb(msg)


def decode_depth(msg) -> np.ndarray:
    """Image or compressedDepth CompressedImage -> float32 [H, W] metres, 0 = invalid."""
    return compressed_depth_to_metres(msg) if hasattr(msg, "format") else raw_to_depth(msg)


# ------------------------------------------------------------------------------ encoding (for writers)

def encode_jpeg(rgb: np.ndarray, quality: int = 95) -> bytes:
    """uint8 [H, W, 3] RGB -> JPEG bytes (format 'rgb8; jpeg compressed bgr8', as image_transport writes)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.asarray(rgb, np.uint8), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ImageDecodeError("JPEG encoding failed")
    return buf.tobytes()


def encode_compressed_depth(depth_m: np.ndarray) -> bytes:
    """float32 [H, W] metres -> compressedDepth bytes for format '16UC1; compressedDepth png'
    (12-byte header: PNG format, zero quantisation; then a 16-bit PNG of millimetres)."""
    import cv2

    d = np.asarray(depth_m, np.float64) * 1000.0
    mm = np.where(np.isfinite(d) & (d > 0), np.rint(d), 0).clip(0, 65535).astype(np.uint16)
    ok, buf = cv2.imencode(".png", mm)
    if not ok:
        raise ImageDecodeError("PNG encoding failed")
    return struct.pack("<iff", _CD_PNG, 0.0, 0.0) + buf.tobytes()


def camera_info_K(info) -> tuple[np.ndarray, tuple[int, int]]:
    """sensor_msgs/CameraInfo -> (K [3, 3] float64 in OpenCV pixel coordinates, (width, height));
    ValueError for an empty size, NaN/inf, a zero focal length (uncalibrated) or a non-pinhole K."""
    w, h = int(info.width), int(info.height)
    if w == 0 or h == 0:
        raise ValueError(f"CameraInfo: image size {w}x{h} is empty")
    K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(K).all():
        raise ValueError("CameraInfo: K contains NaN or inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"CameraInfo: focal lengths must be > 0, got fx={K[0, 0]}, fy={K[1, 1]} "
                         "(an all-zero K means the camera is uncalibrated)")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise ValueError(f"CameraInfo: K is not a pinhole matrix: {K.tolist()}")
    return K, (w, h)
