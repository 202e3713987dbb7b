"""Sections of the synthetic scene generator (`rg synth`) and of the main job (`rg demo`)."""
from __future__ import annotations

from typing import Annotated, Literal

from annotated_types import Interval

from .schema import section


@section
class SynthConfig:
    """Synthetic scene generator (`rg synth`)."""

    views: int = 100
    """Number of rendered views on the ring around the table."""
    width: int = 320
    """Image width in pixels."""
    height: int = 240
    """Image height in pixels."""
    objects: int = 7
    """Number of objects dropped on the table."""
    same_category: Annotated[int, Interval(ge=0)] = 0
    """Of those, how many share a category with another one (several cups of different colours,
    two screwdrivers: what "the red cup" and "the second cup from the left" need); 0: one object per
    category while categories last."""
    seed: int = 0
    """Random seed: same seed, same scene, byte for byte."""
    fov_y_deg: float = 60.0
    """Vertical field of view of the pinhole camera."""
    near: float = 0.02
    """Renderer near plane (m)."""
    far: float = 20.0
    """Renderer far plane (m); depth beyond it (the sky) is stored as invalid (0)."""
    test_every: int = 8
    """Every n-th view (index % n == 0) goes to transforms_test.json."""
    ring_radius: tuple[float, float] = (0.38, 0.62)
    """Min/max horizontal camera distance from the table centre (m)."""
    ring_height: tuple[float, float] = (0.25, 0.50)
    """Min/max camera height above the table top (m)."""
    settle_steps: int = 480
    """Physics steps (240 Hz) to let dropped objects settle."""
    spread: float = 0.16
    """Half-width (m) of the square on the table where objects are dropped."""
    layout: Literal["table", "room"] = "table"
    """table: objects on one table, views on a ring around it. room: `tables` tables on a grid
    `table_spacing` apart, the objects shared among them, and a camera that walks from table to
    table (an arc around each, at a robot's head height): room-scale mapping and memory."""
    tables: Annotated[int, Interval(ge=1)] = 4
    """Tables of the room layout."""
    table_spacing: Annotated[float, Interval(gt=1.6)] = 3.0
    """Distance between neighbouring table centres (m); 4 tables 3 m apart span 4.5 x 4 m."""
    room_spread: Annotated[float, Interval(gt=0.0, le=0.45)] = 0.32
    """Half-width (m) of the square on each room table where its objects are dropped."""
    room_radius: tuple[float, float] = (0.9, 1.3)
    """Min/max horizontal distance (m) of the room walk from each table's centre (a robot passing
    by; (0.45, 0.7) is one stepping up to the table, objects as large in the image as on the table top)."""
    room_height: tuple[float, float] = (0.9, 1.3)
    """Min/max camera height above the floor (m) on the room walk (the table top is at 0.63 m)."""
    point_cloud_voxel: float = 0.005
    """Voxel size (m) of points3d.ply."""
    workers: int = 2
    """Processes that render views in parallel (output does not depend on it)."""


@section
class DemoConfig:
    """The main job (`rg demo`) on an embedded default scene."""

    views: int = 24
    width: int = 320
    height: int = 240
    objects: int = 5
    seed: int = 0
    sheet_views: int = 4
    """How many views the contact sheet shows."""
    ground: bool = True
    """Also map the scene, supervise it, train the field and answer one explicit and one implicit query."""
    supervision: str = "oracle"
    """2D supervision of the demo map: "oracle" (ground-truth masks and names: shows the 3D pipeline
    itself) or "default" (the offline mask generator and ConSE, whose names are often wrong)."""
    field_seconds: float = 0.0
    """Feature-training seconds of the demo; 0: until the field converges (field.seconds the ceiling)."""
