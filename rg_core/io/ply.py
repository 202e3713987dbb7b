"""Point clouds as binary little-endian PLY (x, y, z float32; red, green, blue uchar).

Written with numpy so the bytes are deterministic; open3d and any PLY reader load them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .images import SceneError

_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """points [N, 3] float, colors [N, 3] uint8 (grey if None)."""
    points = np.asarray(points)
    assert points.ndim == 2 and points.shape[1] == 3, points.shape
    if colors is None:
        colors = np.full((len(points), 3), 128, np.uint8)
    assert colors.shape == points.shape, (colors.shape, points.shape)
    rec = np.empty(len(points), _DTYPE)
    for k, name in enumerate("xyz"):
        rec[name] = points[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        rec[name] = colors[:, k]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """-> points [N, 3] float32, colors [N, 3] uint8, for PLY files this module writes."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise SceneError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise SceneError(f"{path}: only binary little-endian PLY from write_ply is supported")
    n = next(int(ln.split()[2]) for ln in header if ln.startswith("element vertex"))
    body = data[end + len(b"end_header\n"):]
    if len(body) != n * _DTYPE.itemsize:
        raise SceneError(f"{path}: expected {n} vertices ({n * _DTYPE.itemsize} bytes), got {len(body)} bytes")
    rec = np.frombuffer(body, _DTYPE)
    pts = np.stack([rec["x"], rec["y"], rec["z"]], 1)
    col = np.stack([rec["red"], rec["green"], rec["blue"]], 1)
    return pts, col
