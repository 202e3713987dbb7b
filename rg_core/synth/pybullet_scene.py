"""pybullet pieces of the synthetic generator: physics settling and headless TinyRenderer views.

Kept apart from the file writing so that worker processes can rebuild the settled scene from a
plain description (URDF path, scale, pose) and render their share of the views.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import CACHE_DIR
from ..geometry.conventions import CV_FROM_GL


@dataclass(frozen=True)
class PlacedObject:
    """An object as it rests after settling; enough to rebuild it in another process."""

    object_id: int          # instance id in masks (1..K)
    urdf: str
    scale: float
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]  # xyzw


def _connect():
    import pybullet as p
    import pybullet_data

    cid = p.connect(p.DIRECT)
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    return p, cid


@functools.lru_cache(maxsize=None)
def loadable_urdf(urdf: str) -> str:
    """The URDF to hand pybullet for `urdf` (a pybullet_data-relative or absolute path).

    pybullet_data's toys/concave_box.urdf (the catalogue's "toy box") names a collision file
    concave_box.cdf that pybullet_data does not ship, and has mass 0, so loadURDF failed ("Cannot
    load URDF file") for every fallback scene that drew it. Such a URDF is rewritten once into
    ~/.cache/reasongrounder/urdf/ with the visual mesh, by absolute path, as its collision shape
    and a small mass; any other URDF is returned unchanged.
    """
    import xml.etree.ElementTree as ET

    import pybullet_data

    src = Path(urdf) if Path(urdf).is_absolute() else Path(pybullet_data.getDataPath()) / urdf
    if not src.is_file():
        return urdf
    root = ET.parse(src).getroot()
    missing = [c for c in root.iter("cdf") if not (src.parent / c.get("filename", "")).is_file()]
    if not missing:
        return urdf
    out = Path(CACHE_DIR).expanduser() / "urdf" / src.name
    for mesh in root.iter("mesh"):
        mesh.set("filename", str((src.parent / mesh.get("filename", "")).resolve()))
    visual = next(root.iter("visual")).find("geometry/mesh")
    for geom in root.iter("geometry"):
        for c in geom.findall("cdf"):
            geom.remove(c)
            geom.append(ET.Element("mesh", {"filename": visual.get("filename"), "scale": c.get("scale", "1 1 1")}))
    for mass in root.iter("mass"):
        if float(mass.get("value", "0")) <= 0:
            mass.set("value", "0.2")
    for inertia in root.iter("inertia"):
        for k in ("ixx", "iyy", "izz"):
            inertia.set(k, "0.001")
    text = ET.tostring(root, encoding="unicode")
    if not out.is_file() or out.read_text() != text:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(f".{id(text)}.tmp")
        tmp.write_text(text)
        tmp.replace(out)
    return str(out)


def load_static_scene(objects: list[PlacedObject], with_table: bool = True,
                      tables: tuple[tuple[float, float], ...] = ((0.0, 0.0),)):
    """A client holding the floor, the tables (centres x, y) and the given objects at fixed poses.

    Returns (pybullet module, client id, {object_id: body uid}).
    """
    p, cid = _connect()
    if with_table:
        p.loadURDF("plane.urdf", physicsClientId=cid)
        for x, y in tables:
            p.loadURDF("table/table.urdf", [x, y, 0.0], useFixedBase=True, physicsClientId=cid)
    uids = {}
    for o in objects:
        uids[o.object_id] = p.loadURDF(loadable_urdf(o.urdf), list(o.position), list(o.orientation), useFixedBase=True,
                                       globalScaling=o.scale, physicsClientId=cid)
    return p, cid, uids


def table_top() -> tuple[np.ndarray, np.ndarray]:
    """(aabb_min, aabb_max) of pybullet_data's table."""
    p, cid = _connect()
    t = p.loadURDF("table/table.urdf", useFixedBase=True, physicsClientId=cid)
    lo, hi = p.getAABB(t, physicsClientId=cid)
    p.disconnect(cid)
    return np.array(lo), np.array(hi)


def settle(urdfs: list[tuple[str, float]], rng: np.random.Generator, spread: float, steps: int,
           tables: tuple[tuple[float, float], ...] = ((0.0, 0.0),)) -> list[PlacedObject]:
    """Drop objects onto the tables (object i on table i mod T) and let physics settle them so they
    touch, lean and occlude."""
    p, cid = _connect()
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    p.setPhysicsEngineParameter(deterministicOverlappingPairs=1, physicsClientId=cid)
    p.loadURDF("plane.urdf", physicsClientId=cid)
    ids = [p.loadURDF("table/table.urdf", [x, y, 0.0], useFixedBase=True, physicsClientId=cid) for x, y in tables]
    top = p.getAABB(ids[0], physicsClientId=cid)[1][2]
    bodies = []
    for i, (urdf, scale) in enumerate(urdfs):
        xy = rng.uniform(-spread, spread, size=2) + np.asarray(tables[i % len(tables)])
        z = top + 0.06 + 0.05 * (i // len(tables))  # staggered so later objects land on or against earlier ones
        tilt = rng.uniform(-0.6, 0.6, size=2) if rng.random() < 0.3 else np.zeros(2)
        orn = p.getQuaternionFromEuler([tilt[0], tilt[1], rng.uniform(-np.pi, np.pi)])
        uid = p.loadURDF(loadable_urdf(urdf), [xy[0], xy[1], z], orn, globalScaling=scale, physicsClientId=cid)
        # Round fruit would roll off the table: rolling/spinning friction and damping keep it.
        p.changeDynamics(uid, -1, lateralFriction=0.8, rollingFriction=0.002, spinningFriction=0.002,
                         linearDamping=0.2, angularDamping=0.4, physicsClientId=cid)
        bodies.append(uid)
    for _ in range(steps):
        p.stepSimulation(physicsClientId=cid)
    placed = []
    for i, (uid, (urdf, scale)) in enumerate(zip(bodies, urdfs)):
        pos, orn = p.getBasePositionAndOrientation(uid, physicsClientId=cid)
        # Round to 1e-6 so the description is stable text and rebuilds identically elsewhere.
        placed.append(PlacedObject(i + 1, urdf, scale, tuple(round(float(v), 6) for v in pos),
                                   tuple(round(float(v), 6) for v in orn)))
    p.disconnect(cid)
    return placed


def gl_matrices(K: np.ndarray, c2w: np.ndarray, width: int, height: int, near: float, far: float):
    """OpenGL view and projection matrices (column-major lists) for an OpenCV camera.

    TinyRenderer samples pixel (i, j) at the pixel's corner and flips rows, which shifts the image
    by (+0.5, -0.5) pixels against the pinhole model; the projection matrix takes that back so that
    the stored K is exact (checked by the reprojection tests).
    """
    fx, fy = K[0, 0], K[1, 1]
    cx, cy = K[0, 2] - 0.5, K[1, 2] + 0.5
    P = np.array([
        [2 * fx / width, 0.0, 1.0 - 2.0 * (cx + 0.5) / width, 0.0],
        [0.0, 2 * fy / height, 2.0 * (cy + 0.5) / height - 1.0, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2.0 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])
    V = CV_FROM_GL @ np.linalg.inv(c2w)
    return V.T.flatten().tolist(), P.T.flatten().tolist()


def render(p, cid, K, c2w, width, height, near, far, light=(0.4, -0.3, 1.0)):
    """-> rgb uint8 [H, W, 3], metric z-depth float32 [H, W] (0 beyond far), seg int32 [H, W]."""
    view, proj = gl_matrices(K, c2w, width, height, near, far)
    _, _, rgba, zbuf, seg = p.getCameraImage(width, height, viewMatrix=view, projectionMatrix=proj,
                                             renderer=p.ER_TINY_RENDERER, lightDirection=list(light),
                                             shadow=0, physicsClientId=cid)
    rgba = np.reshape(np.asarray(rgba, dtype=np.uint8), (height, width, 4))
    zbuf = np.reshape(np.asarray(zbuf, dtype=np.float64), (height, width))
    seg = np.reshape(np.asarray(seg, dtype=np.int64), (height, width))
    depth = far * near / (far - (far - near) * zbuf)
    depth[zbuf >= 1.0 - 1e-7] = 0.0
    return rgba[..., :3].copy(), depth.astype(np.float32), seg


def mesh_aabb(p, cid, uid) -> tuple[np.ndarray, np.ndarray]:
    """World AABB of a body's visual meshes (tighter than pybullet's collision AABB)."""
    pos, orn = p.getBasePositionAndOrientation(uid, physicsClientId=cid)
    R = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
    pts = []
    for vs in p.getVisualShapeData(uid, physicsClientId=cid):
        mesh = Path(vs[4].decode()) if isinstance(vs[4], bytes) else Path(vs[4])
        if vs[2] != p.GEOM_MESH or not mesh.is_file() or mesh.suffix.lower() != ".obj":
            continue
        v = np.array([[float(x) for x in ln.split()[1:4]] for ln in mesh.read_text(errors="ignore").splitlines()
                      if ln.startswith("v ")])
        v = v * np.asarray(vs[3])
        lp, lo = vs[5], vs[6]
        Rl = np.array(p.getMatrixFromQuaternion(lo)).reshape(3, 3)
        pts.append((v @ Rl.T + lp) @ R.T + pos)
    if not pts:  # primitive shapes: fall back to the collision AABB
        lo, hi = p.getAABB(uid, physicsClientId=cid)
        return np.array(lo), np.array(hi)
    allp = np.concatenate(pts)
    return allp.min(0), allp.max(0)
