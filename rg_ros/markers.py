"""GroundingResult -> visualization_msgs/MarkerArray for RViz (no rclpy here, only message types).

Per grounded object: an oriented box as LINE_LIST edges, the same box as a translucent CUBE and a
TEXT_VIEW_FACING label above it. The array starts with a DELETEALL marker so that the boxes of the
previous query disappear. The scene graph: one text label per object (`graph_markers`).
"""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from rg_core.geometry.rotations import rot_to_quat
from rg_core.grounding.result import GroundingResult

NS = "rg_grounding"
PALETTE = [(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16), (0.58, 0.4, 0.74),
           (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5)]
# The 12 edges of a box as index pairs into its 8 corners (corner bits: x, y, z sign).
EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def box_corners(center: np.ndarray, rotation: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """[8, 3] corners of an oriented box (rotation columns are the box axes, extent full lengths)."""
    signs = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64) * 2 - 1   # [8, 3]
    half = np.asarray(extent, np.float64).reshape(3) / 2
    return np.asarray(center, np.float64).reshape(3) + (signs * half) @ np.asarray(rotation, np.float64).reshape(3, 3).T


def _proper(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, np.float64).reshape(3, 3)
    return R * np.array([1.0, 1.0, -1.0]) if np.linalg.det(R) < 0 else R   # a reflected frame, same box


def result_markers(result: GroundingResult, frame_id: str, stamp: Time | None = None, line_width: float = 0.005,
                   box_alpha: float = 0.25, text_height: float = 0.04, lifetime: float = 0.0) -> MarkerArray:
    """Markers for every object of `result` (only the DELETEALL marker when it has none)."""
    hdr = Header(frame_id=frame_id, stamp=stamp if stamp is not None else Time())
    life = Duration(sec=int(lifetime), nanosec=int((lifetime % 1) * 1e9))
    out = [Marker(header=hdr, ns=NS, id=0, action=Marker.DELETEALL)]
    label = result.target or result.query
    for i, obj in enumerate(result.objects):
        r, g, b = PALETTE[i % len(PALETTE)]
        center = np.asarray(obj.obb_center, np.float64).reshape(3)
        R = _proper(obj.obb_rotation)
        extent = np.asarray(obj.obb_extent, np.float64).reshape(3)
        if not (np.isfinite(center).all() and np.isfinite(R).all() and np.isfinite(extent).all()):
            continue
        corners = box_corners(center, R, extent)
        qx, qy, qz, qw = rot_to_quat(R)
        pose = Pose(position=Point(x=float(center[0]), y=float(center[1]), z=float(center[2])),
                    orientation=Quaternion(x=float(qx), y=float(qy), z=float(qz), w=float(qw)))
        edges = Marker(header=hdr, ns=NS, id=3 * i + 1, type=Marker.LINE_LIST, action=Marker.ADD, lifetime=life,
                       scale=Vector3(x=float(line_width)), color=ColorRGBA(r=r, g=g, b=b, a=1.0))
        edges.pose.orientation.w = 1.0
        edges.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for a, b_ in EDGES for p in (corners[a], corners[b_])]
        cube = Marker(header=hdr, ns=NS, id=3 * i + 2, type=Marker.CUBE, action=Marker.ADD, lifetime=life, pose=pose,
                      scale=Vector3(x=float(max(extent[0], 1e-4)), y=float(max(extent[1], 1e-4)),
                                    z=float(max(extent[2], 1e-4))),
                      color=ColorRGBA(r=r, g=g, b=b, a=float(box_alpha)))
        top = float(corners[:, 2].max()) + text_height
        text = Marker(header=hdr, ns=NS, id=3 * i + 3, type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, lifetime=life,
                      scale=Vector3(z=float(text_height)), color=ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0),
                      text=f"{label} {obj.confidence:.2f}" if label else f"#{i} {obj.confidence:.2f}")
        text.pose.position = Point(x=float(center[0]), y=float(center[1]), z=top)
        text.pose.orientation.w = 1.0
        out += [edges, cube, text]
    return MarkerArray(markers=out)


GRAPH_NS = "rg_scene_graph"


def graph_markers(objs: list, up: np.ndarray, frame_id: str, stamp: Time | None = None,
                  text_height: float = 0.03) -> MarkerArray:
    """A TEXT_VIEW_FACING label "name (colour)" above each scene-graph object (relations.SceneObject),
    after a DELETEALL of the namespace."""
    hdr = Header(frame_id=frame_id, stamp=stamp if stamp is not None else Time())
    up = np.asarray(up, np.float64).reshape(3)
    out = [Marker(header=hdr, ns=GRAPH_NS, id=0, action=Marker.DELETEALL)]
    for i, o in enumerate(objs):
        lo, hi = np.asarray(o.obj.aabb_min, np.float64), np.asarray(o.obj.aabb_max, np.float64)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            continue
        top = (lo + hi) / 2 + up * (abs(up) @ (hi - lo) / 2 + text_height)   # just above the box along up
        text = Marker(header=hdr, ns=GRAPH_NS, id=i + 1, type=Marker.TEXT_VIEW_FACING, action=Marker.ADD,
                      scale=Vector3(z=float(text_height)), color=ColorRGBA(r=1.0, g=1.0, b=0.6, a=1.0),
                      text=f"{o.name} ({o.colour})" if o.colour else o.name)
        text.pose.position = Point(x=float(top[0]), y=float(top[1]), z=float(top[2]))
        text.pose.orientation.w = 1.0
        out.append(text)
    return MarkerArray(markers=out)
