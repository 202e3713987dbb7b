"""rg_core.geometry.tf_buffer: tf2 semantics (chains, static, interpolation, cache, errors)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rg_core.geometry.rotations import quat_to_rot
from rg_core.geometry.tf_buffer import (
    ConnectivityError,
    ExtrapolationError,
    GapError,
    PastExtrapolationError,
    InvalidTransformError,
    LoopError,
    TFBuffer,
    slerp,
)

RNG = np.random.default_rng(7)


def rand_quat():
    q = RNG.normal(size=4)
    return q / np.linalg.norm(q)


def rz(angle):
    return np.array([0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)])


def mat(t, q):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quat_to_rot(q), t
    return T


def test_chain_through_common_ancestor_matches_matrix_product():
    """map -> odom -> base_link -> camera, and map -> marker: any pair is the product of the links."""
    b = TFBuffer()
    links = {("map", "odom"): (RNG.normal(size=3), rand_quat()), ("odom", "base_link"): (RNG.normal(size=3), rand_quat()),
             ("base_link", "cam"): (RNG.normal(size=3), rand_quat()), ("map", "marker"): (RNG.normal(size=3), rand_quat())}
    for (p, c), (t, q) in links.items():
        b.set_transform(p, c, 5.0, t, q, static=(c == "cam"))
    M = {k: mat(*v) for k, v in links.items()}
    map_cam = M["map", "odom"] @ M["odom", "base_link"] @ M["base_link", "cam"]
    np.testing.assert_allclose(b.lookup("map", "cam", 5.0), map_cam, atol=1e-12)
    np.testing.assert_allclose(b.lookup("cam", "map", 5.0), np.linalg.inv(map_cam), atol=1e-12)
    marker_cam = np.linalg.inv(M["map", "marker"]) @ map_cam   # up to map, down to marker
    np.testing.assert_allclose(b.lookup("marker", "cam", 5.0), marker_cam, atol=1e-12)
    np.testing.assert_allclose(b.lookup("/odom", "odom", 5.0), np.eye(4))   # leading slash ignored
    # time 0 = latest common time (5.0 here)
    np.testing.assert_allclose(b.lookup("map", "cam"), map_cam, atol=1e-12)


def test_long_chain():
    b = TFBuffer()
    T = np.eye(4)
    for i in range(60):
        t, q = RNG.normal(size=3) * 0.1, rand_quat()
        b.set_transform(f"f{i}", f"f{i + 1}", 1.0, t, q)
        T = T @ mat(t, q)
    np.testing.assert_allclose(b.lookup("f0", "f60", 1.0), T, atol=1e-9)


def test_interpolation_linear_and_slerp():
    b = TFBuffer()
    b.set_transform("odom", "base", 1.0, [0, 0, 0], rz(0.0))
    b.set_transform("odom", "base", 3.0, [2, -4, 1], rz(1.0))
    T = b.lookup("odom", "base", 1.5)
    np.testing.assert_allclose(T[:3, 3], [0.5, -1.0, 0.25], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], quat_to_rot(rz(0.25)), atol=1e-12)   # rotation angle is linear in time
    np.testing.assert_allclose(b.lookup("odom", "base", 3.0)[:3, 3], [2, -4, 1])
    # slerp takes the short arc even when the quaternions have opposite signs
    q = slerp(rz(0.2), -rz(0.4), 0.5)
    np.testing.assert_allclose(quat_to_rot(q), quat_to_rot(rz(0.3)), atol=1e-12)
    # nearly equal quaternions: no division by sin(0)
    q = slerp(rz(0.1), rz(0.1 + 1e-9), 0.5)
    assert np.isfinite(q).all() and abs(np.linalg.norm(q) - 1) < 1e-12


def test_static_valid_at_all_times_dynamic_extrapolation_errors_name_frames_and_times():
    b = TFBuffer()
    b.set_transform("base_link", "camera_color_optical_frame", 0.0, [0.1, 0, 0.3], rz(0.5), static=True)
    b.set_transform("odom", "base_link", 10.0, [0, 0, 0], rz(0))
    b.set_transform("odom", "base_link", 11.0, [1, 0, 0], rz(0))
    for t in (10.0, 10.5, 11.0):
        b.lookup("odom", "camera_color_optical_frame", t)
    assert b.lookup("base_link", "camera_color_optical_frame", 1e6)[2, 3] == pytest.approx(0.3)   # static: any time
    with pytest.raises(ExtrapolationError, match=r"into the future.*11\.5.*11\.0.*camera_color_optical_frame.*odom") as info:
        b.lookup("odom", "camera_color_optical_frame", 11.5)
    assert not isinstance(info.value, (PastExtrapolationError, GapError))   # the future may still come: a live node waits
    with pytest.raises(PastExtrapolationError, match=r"into the past.*9\.0.*10\.0"):
        b.lookup("odom", "camera_color_optical_frame", 9.0)
    lenient = TFBuffer(extrapolation_limit=0.6)
    lenient.set_transform("odom", "base_link", 10.0, [0, 0, 0], rz(0))
    lenient.set_transform("odom", "base_link", 11.0, [1, 0, 0], rz(0))
    assert lenient.lookup("odom", "base_link", 11.5)[0, 3] == 1.0     # the nearest sample
    with pytest.raises(ExtrapolationError):
        lenient.lookup("odom", "base_link", 11.7)


def test_latest_common_time():
    b = TFBuffer()
    b.set_transform("map", "odom", 4.0, [1, 0, 0], rz(0))
    b.set_transform("map", "odom", 6.0, [3, 0, 0], rz(0))
    b.set_transform("odom", "base", 2.0, [0, 0, 0], rz(0))
    b.set_transform("odom", "base", 5.0, [0, 1, 0], rz(0))
    np.testing.assert_allclose(b.lookup("map", "base")[:3, 3], [2, 1, 0])   # at t = 5 (min of the newest)


def test_cache_time_bounds_history_and_old_data_is_refused():
    b = TFBuffer(cache_time=2.0)
    for i in range(100):
        b.set_transform("odom", "base", float(i) * 0.1, [i, 0, 0], rz(0))
    assert len(b._stamps["base"]) <= 21 and b._stamps["base"][0] >= 9.9 - 2.0 - 1e-9
    with pytest.raises(PastExtrapolationError, match="past"):
        b.lookup("odom", "base", 5.0)
    with pytest.raises(ExtrapolationError, match="older than the buffer keeps"):
        b.set_transform("odom", "base", 1.0, [0, 0, 0], rz(0))
    assert b.rejected == 1


def test_max_gap_refuses_interpolation_across_a_dropout():
    b = TFBuffer(max_gap=0.25)
    for t in (0.0, 0.1, 0.2, 0.6, 0.7):
        b.set_transform("odom", "base", t, [t, 0, 0], rz(0))
    assert b.lookup("odom", "base", 0.15)[0, 3] == pytest.approx(0.15)
    with pytest.raises(GapError, match=r"gap of 0\.400 s"):
        b.lookup("odom", "base", 0.4)
    assert b.lookup("odom", "base", 0.6)[0, 3] == pytest.approx(0.6)   # exact samples at the gap's ends work
    tf2_like = TFBuffer()
    for t in (0.0, 0.6):
        tf2_like.set_transform("odom", "base", t, [t, 0, 0], rz(0))
    assert tf2_like.lookup("odom", "base", 0.4)[0, 3] == pytest.approx(0.4)


def test_missing_link_names_both_frames():
    b = TFBuffer()
    b.set_transform("map", "odom", 1.0, [0, 0, 0], rz(0))
    b.set_transform("base_link", "camera", 1.0, [0, 0, 0], rz(0), static=True)
    with pytest.raises(ConnectivityError, match=r"'map' and 'camera'.*not part of the same tree"):
        b.lookup("map", "camera", 1.0)
    with pytest.raises(ConnectivityError, match=r"\"nowhere\".*does not exist.*known frames: base_link, camera, map, odom"):
        b.lookup("map", "nowhere", 1.0)
    ok, why = b.can_transform("map", "camera", 1.0)
    assert not ok and "not part of the same tree" in why


@pytest.mark.parametrize("bad, match", [
    (dict(translation=[np.nan, 0, 0]), "NaN"),
    (dict(rotation=[0, 0, 0, np.inf]), "NaN or inf"),
    (dict(rotation=[0, 0, 0, 2.0]), "not normalised"),
    (dict(rotation=[0, 0, 0, 0]), "not normalised"),
    (dict(parent="cam"), "own parent"),
    (dict(parent=""), "must not be empty"),
    (dict(stamp=float("nan")), "NaN"),
])
def test_bad_transforms_are_refused_and_leave_the_buffer_intact(bad, match):
    b = TFBuffer()
    b.set_transform("base", "cam", 1.0, [1, 2, 3], rz(0.3))
    before = b.lookup("base", "cam", 1.0)
    args = dict(parent="base", child="cam", stamp=2.0, translation=[0, 0, 0], rotation=rz(0))
    args.update(bad)
    with pytest.raises(InvalidTransformError, match=match):
        b.set_transform(**args)
    np.testing.assert_array_equal(b.lookup("base", "cam", 1.0), before)
    assert b.rejected == 1


def test_loops_are_refused_at_insertion_and_detected_at_lookup():
    b = TFBuffer()
    b.set_transform("a", "b", 1.0, [0, 0, 0], rz(0))
    b.set_transform("b", "c", 1.0, [0, 0, 0], rz(0))
    with pytest.raises(LoopError, match="a -> c -> b -> a"):
        b.set_transform("c", "a", 1.0, [0, 0, 0], rz(0))
    np.testing.assert_allclose(b.lookup("a", "c", 1.0), np.eye(4))
    # a loop that exists only at an earlier time (re-parenting) is found when looking up there
    b2 = TFBuffer()
    b2.set_transform("x", "y", 1.0, [0, 0, 0], rz(0))
    b2.set_transform("z", "y", 2.0, [0, 0, 0], rz(0))   # y re-parented from x to z at t = 2
    b2.set_transform("y", "x", 3.0, [0, 0, 0], rz(0))   # fine at the newest time: x <- y <- z ... no cycle
    b2._static["z"] = b2._dynamic["x"][0].__class__(0.0, "x", np.zeros(3), rz(0))   # z <- x as a static link
    with pytest.raises(LoopError, match="loop"):
        b2.lookup("x", "z", 2.5)


def test_reparenting_uses_the_parent_at_the_stamp():
    b = TFBuffer()
    b.set_transform("map", "odom", 0.0, [10, 0, 0], rz(0), static=True)
    b.set_transform("map", "robot", 1.0, [1, 0, 0], rz(0))
    b.set_transform("map", "robot", 2.0, [2, 0, 0], rz(0))
    b.set_transform("odom", "robot", 3.0, [0, 5, 0], rz(0))
    b.set_transform("odom", "robot", 4.0, [0, 6, 0], rz(0))
    np.testing.assert_allclose(b.lookup("map", "robot", 1.5)[:3, 3], [1.5, 0, 0])
    np.testing.assert_allclose(b.lookup("map", "robot", 3.5)[:3, 3], [10, 5.5, 0])
