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


def _read_header(path: Path, eol: bytes) -> tuple[bytes, int, list[str]]:
    """-> (the file's bytes, where `end_header` starts, the header lines before it); SceneError when
    the file is missing or does not start like a PLY. Both readers open files this way; `eol` b"\n"
    holds `ply` and `end_header` to write_ply's own line ends, b"" accepts any line end."""
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    data = path.read_bytes()
    end = data.find(b"end_header" + eol)
    if not data.startswith(b"ply" + eol) or end < 0:
        raise SceneError(f"{path}: not a PLY file")
    return data, end, data[:end].decode("ascii", errors="replace").splitlines()


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """-> points [N, 3] float32, colors [N, 3] uint8, for PLY files this module writes."""
    path = Path(path)
    data, end, header = _read_header(path, b"\n")
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


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Any binary little-endian or ASCII PLY mesh (e.g. BOP object models) -> vertices [N, 3]
    float64 (file units), triangles [F, 3] int64 (empty when the file has no faces). Faces must be
    triangles; extra vertex properties (normals, colours, texture coordinates) are skipped."""
    path = Path(path)
    data, end, header = _read_header(path, b"")
    body_start = data.index(b"\n", end) + 1
    fmt = next((ln.split()[1] for ln in header if ln.startswith("format")), "")
    if fmt not in ("binary_little_endian", "ascii"):
        raise SceneError(f"{path}: PLY format {fmt!r} not supported (binary_little_endian or ascii)")
    elements: list[list] = []  # [name, count, [(prop name, dtype) | ("list", count dtype, item dtype)]]
    for ln in header:
        t = ln.split()
        if t and t[0] == "element":
            elements.append([t[1], int(t[2]), []])
        elif t and t[0] == "property" and elements:
            if t[1] == "list":
                elements[-1][2].append(("list", _PLY_TYPES[t[2]], _PLY_TYPES[t[3]]))
            else:
                elements[-1][2].append((t[2], _PLY_TYPES[t[1]]))
    if not elements or elements[0][0] != "vertex":
        raise SceneError(f"{path}: the first PLY element must be 'vertex'")
    verts = faces = None
    if fmt == "ascii":
        rows = data[body_start:].decode("ascii", errors="replace").splitlines()
        nv = elements[0][1]
        names = [p[0] for p in elements[0][2]]
        arr = np.array([r.split()[: len(names)] for r in rows[:nv]], np.float64)
        verts = arr[:, [names.index(c) for c in "xyz"]]
        if len(elements) > 1 and elements[1][0] == "face":
            f = [r.split() for r in rows[nv: nv + elements[1][1]]]
            if any(r[0] != "3" for r in f):
                raise SceneError(f"{path}: only triangle faces are supported")
            faces = np.array([r[1:4] for r in f], np.int64)
    else:
        off = body_start
        for name, count, props in elements:
            if any(p[0] == "list" for p in props):
                if name != "face" or len(props) != 1:
                    raise SceneError(f"{path}: list properties are supported only as face vertex indices")
                _, cdt, idt = props[0]
                dt = np.dtype([("n", "<" + cdt), ("i", "<" + idt, 3)])
                rec = np.frombuffer(data, dt, count, off)
                if count and not np.all(rec["n"] == 3):
                    raise SceneError(f"{path}: only triangle faces are supported")
                faces = rec["i"].astype(np.int64)
                off += dt.itemsize * count
                continue
            dt = np.dtype([(p[0], "<" + p[1]) for p in props])
            if off + dt.itemsize * count > len(data):
                raise SceneError(f"{path}: file ends inside element '{name}'")
            rec = np.frombuffer(data, dt, count, off)
            off += dt.itemsize * count
            if name == "vertex":
                verts = np.stack([rec[c].astype(np.float64) for c in "xyz"], 1)
    if verts is None or not len(verts):
        raise SceneError(f"{path}: no vertices")
    faces = np.zeros((0, 3), np.int64) if faces is None else faces
    if len(faces) and (faces.min() < 0 or faces.max() >= len(verts)):
        raise SceneError(f"{path}: face indices outside the {len(verts)} vertices")
    return verts, faces
