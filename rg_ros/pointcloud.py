"""PointCloud2 <-> numpy with structured dtypes (sensor_msgs_py is not on PyPI).

Writes xyz float32 plus the packed float32 `rgb` field RViz expects (0x00RRGGBB bits in a float32).
Reads any layout whose x, y, z are float32/float64 scalars, honouring offsets, point_step,
row_step and endianness; colour from a packed `rgb`/`rgba` field or separate uint8 r, g, b fields.
"""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

# PointField datatype -> numpy type character (sizes 1, 1, 2, 2, 4, 4, 4, 8 bytes).
_DTYPES = {PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2", PointField.UINT16: "u2",
           PointField.INT32: "i4", PointField.UINT32: "u4", PointField.FLOAT32: "f4", PointField.FLOAT64: "f8"}
_XYZRGB = np.dtype({"names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", "<u4"],
                    "offsets": [0, 4, 8, 12], "itemsize": 16})


def to_pointcloud2(points: np.ndarray, colors: np.ndarray | None = None, frame_id: str = "",
                   stamp: Time | None = None) -> PointCloud2:
    """points [N, 3] float, colors [N, 3] uint8 RGB or None -> an unorganised (height 1) cloud."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape [N, 3], got {pts.shape}")
    n = pts.shape[0]
    fields = [PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, c in enumerate("xyz")]
    if colors is None:
        buf = np.ascontiguousarray(pts.astype("<f4")).tobytes()
        step = 12
    else:
        col = np.asarray(colors)
        if col.shape != (n, 3):
            raise ValueError(f"colors: expected shape [{n}, 3] to match points, got {col.shape}")
        if col.dtype != np.uint8:
            raise ValueError(f"colors: expected uint8 RGB, got {col.dtype}")
        rec = np.empty(n, dtype=_XYZRGB)
        rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
        c = col.astype(np.uint32)
        rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]   # bits of a float32, as RViz reads them
        fields.append(PointField(name="rgb", offset=12, datatype=PointField.FLOAT32, count=1))
        buf = rec.tobytes()
        step = 16
    return PointCloud2(header=Header(frame_id=frame_id, stamp=stamp if stamp is not None else Time()),
                       height=1, width=n, fields=fields, is_bigendian=False, point_step=step,
                       row_step=step * n, data=buf, is_dense=bool(np.isfinite(pts).all()))


def _record_dtype(wanted: dict, order: str, point_step: int) -> np.dtype:
    """The structured dtype of one point: the wanted fields (name -> PointField) at their offsets,
    checked for datatype, count and extent; a packed rgb/rgba is read as its 4 bytes."""
    formats, offsets = [], []
    for name, f in wanted.items():
        if f.datatype not in _DTYPES:
            raise ValueError(f"PointCloud2 field '{name}': unknown datatype {f.datatype}")
        if f.count != 1:
            raise ValueError(f"PointCloud2 field '{name}': count {f.count} not supported (expected 1)")
        code = _DTYPES[f.datatype]
        if name in ("x", "y", "z") and code not in ("f4", "f8"):
            raise ValueError(f"PointCloud2 field '{name}': datatype {code} not supported (float32 or float64)")
        if name in ("rgb", "rgba"):
            if code not in ("f4", "u4", "i4"):
                raise ValueError(f"PointCloud2 field '{name}': packed colour must be 4 bytes, got {code}")
            code = "u4"   # read the float's bits
        if name in ("r", "g", "b") and code != "u1":
            raise ValueError(f"PointCloud2 field '{name}': separate colour channels must be uint8, got {code}")
        end = f.offset + int(code[1])
        if end > point_step:
            raise ValueError(f"PointCloud2 field '{name}' ends at byte {end}, past point_step {point_step}")
        formats.append(order + code)
        offsets.append(f.offset)
    return np.dtype({"names": list(wanted), "formats": formats, "offsets": offsets, "itemsize": point_step})


def from_pointcloud2(msg: PointCloud2) -> tuple[np.ndarray, np.ndarray | None]:
    """A cloud -> (points [N, 3] float32, colors [N, 3] uint8 RGB or None), N = height * width.

    Points are returned as stored (NaNs of a non-dense cloud included)."""
    fields = {f.name: f for f in msg.fields}
    n = msg.height * msg.width
    if n == 0:   # including a default-constructed message without fields
        has_colour = any(k in fields for k in ("rgb", "rgba")) or all(k in fields for k in "rgb")
        return np.zeros((0, 3), np.float32), (np.zeros((0, 3), np.uint8) if has_colour else None)
    for name in "xyz":
        if name not in fields:
            raise ValueError(f"PointCloud2 has no '{name}' field (fields: {sorted(fields)})")

    order = ">" if msg.is_bigendian else "<"
    wanted: dict[str, PointField] = {k: fields[k] for k in "xyz"}
    colour = next((k for k in ("rgb", "rgba") if k in fields), None)
    if colour is not None:
        wanted[colour] = fields[colour]
    elif all(k in fields for k in "rgb"):
        wanted.update({k: fields[k] for k in "rgb"})
    dtype = _record_dtype(wanted, order, msg.point_step)

    row_bytes = msg.width * msg.point_step
    if msg.row_step < row_bytes:
        raise ValueError(f"PointCloud2 row_step {msg.row_step} < width * point_step = {row_bytes}")
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    need = (msg.height - 1) * msg.row_step + row_bytes
    if raw.size < need:
        raise ValueError(f"PointCloud2 data has {raw.size} bytes, layout needs {need}")
    if msg.row_step != row_bytes and msg.height > 1:   # drop row padding: [height, row_step] -> rows
        rows = np.lib.stride_tricks.as_strided(raw, shape=(msg.height, row_bytes), strides=(msg.row_step, 1))
        raw = np.ascontiguousarray(rows).reshape(-1)
    rec = raw[: n * msg.point_step].view(dtype)   # [n] structured

    points = np.stack([rec["x"], rec["y"], rec["z"]], axis=-1).astype(np.float32)
    if colour is not None:
        v = rec[colour].astype(np.uint32)
        colors = np.stack([(v >> 16) & 255, (v >> 8) & 255, v & 255], axis=-1).astype(np.uint8)
    elif "r" in wanted:
        colors = np.stack([rec["r"], rec["g"], rec["b"]], axis=-1).astype(np.uint8)
    else:
        colors = None
    return points, colors
