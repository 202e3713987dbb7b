import numpy as np
import pytest

from rg_core.geometry import conventions as cv


def random_pose(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
    return T


def test_round_trips():
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = random_pose(rng)
        np.testing.assert_allclose(cv.opencv_from_nerf(cv.nerf_from_opencv(T)), T, atol=1e-12)
        np.testing.assert_allclose(cv.optical_from_body(cv.body_from_optical(T)), T, atol=1e-12)
        cv.check_rigid(cv.nerf_from_opencv(T))
        cv.check_rigid(cv.body_from_optical(T))
    assert cv.principal_point_from_corner(*cv.principal_point_to_corner(3.25, 7.5)) == (3.25, 7.5)


def test_axis_meanings():
    # A NeRF camera looks down its -z; the same camera in OpenCV axes looks down +z.
    c2w = cv.look_at([0, 0, 0], [1, 0, 0])
    assert np.allclose(c2w[:3, 2], [1, 0, 0])           # OpenCV forward
    assert np.allclose(c2w[:3, 1], [0, 0, -1])          # OpenCV y is down in the world
    nerf = cv.nerf_from_opencv(c2w)
    assert np.allclose(-nerf[:3, 2], [1, 0, 0])         # NeRF forward is -z
    body = cv.body_from_optical(c2w)
    assert np.allclose(body[:3, 0], [1, 0, 0])          # ROS body x forward
    assert np.allclose(body[:3, 2], [0, 0, 1])          # ROS body z up


def test_backproject_project_round_trip():
    rng = np.random.default_rng(1)
    K = cv.intrinsics_matrix(200.0, 210.0, 79.5, 59.5)
    c2w = random_pose(rng)
    depth = rng.uniform(0.2, 5.0, size=(120, 160))
    pts = cv.backproject(depth, K, c2w).reshape(-1, 3)
    uv, z = cv.project(pts, K, c2w)
    v, u = np.mgrid[0:120, 0:160]
    np.testing.assert_allclose(uv[:, 0], u.ravel(), atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], v.ravel(), atol=1e-6)
    np.testing.assert_allclose(z, depth.ravel(), atol=1e-9)


def test_in_image_keeps_every_pixel_of_the_image_and_nothing_else():
    K = cv.intrinsics_matrix(200.0, 210.0, 79.5, 59.5)
    pts = cv.backproject(np.full((120, 160), 2.0), K, np.eye(4)).reshape(-1, 3)
    uv, z = cv.project(pts, K, np.eye(4))
    assert cv.in_image(uv, z, 160, 120).all()
    u, v = np.round(uv[cv.in_image(uv, z, 160, 120)]).astype(int).T
    assert u.min() == 0 and u.max() == 159 and v.min() == 0 and v.max() == 119
    edge = np.array([[-0.5, 0.0], [-0.51, 0.0], [159.49, 119.49], [159.5, 0.0], [0.0, 119.5], [np.nan, 0.0],
                     [np.inf, 0.0], [10.0, 10.0], [10.0, 10.0]])
    z = np.array([1.0] * 8 + [0.04])
    assert cv.in_image(edge, z, 160, 120, near=0.05).tolist() == [True, False, True, False, False, False, False,
                                                                   True, False]


@pytest.mark.parametrize("T, msg", [
    (np.full((4, 4), np.nan), "NaN"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "orthonormal"),
    (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
    (np.eye(3), "4x4"),
])
def test_check_rigid_rejects(T, msg):
    with pytest.raises(cv.PoseError, match=msg):
        cv.check_rigid(T, "test pose")


def test_up_direction_from_camera_poses():
    from scipy.spatial.transform import Rotation

    ring = [cv.look_at([np.cos(a), np.sin(a), 0.6], [0, 0, 0]) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    assert np.allclose(cv.up_direction(np.stack(ring)), [0, 0, 1], atol=1e-9)
    one = cv.look_at([1.0, 0.0, 1.0], [0, 0, 0])        # one view looking down 45 degrees: its own up
    assert np.allclose(cv.up_direction(one[None]), -one[:3, 1], atol=1e-9)
    R = np.eye(4)
    R[:3, :3] = Rotation.from_euler("xyz", [30, -20, 70], degrees=True).as_matrix()
    assert np.allclose(cv.up_direction(np.stack([R @ T for T in ring])), R[:3, :3] @ [0, 0, 1], atol=1e-9)
    with pytest.raises(ValueError, match="finite"):
        cv.up_direction(np.full((2, 4, 4), np.nan))


def test_up_direction_takes_the_table_where_the_poses_leave_the_pitch_open():
    """Views from one direction (YCB-Video's) leave the pitch open: -y of a camera looking down
    45 degrees is 45 degrees off up, and the table under it tells the rest."""
    rng = np.random.default_rng(0)
    one = np.stack([cv.look_at([1.0, 0.02 * i, 1.0], [0, 0, 0]) for i in range(4)])
    table = np.c_[rng.uniform(-0.5, 0.5, (3000, 2)), rng.normal(0, 0.002, 3000)]          # [3000, 3] z = 0
    mug = np.c_[rng.normal(0, 0.03, (500, 2)), rng.uniform(0, 0.1, 500)]
    assert np.degrees(np.arccos(cv.up_direction(one) @ [0, 0, 1])) > 40
    up = cv.up_direction(one, np.r_[table, mug])
    assert np.degrees(np.arccos(up @ [0, 0, 1])) < 1
    wall = np.c_[rng.normal(0, 0.002, 3000), rng.uniform(-0.5, 0.5, (3000, 2))]          # x = 0: 90 degrees off
    assert np.allclose(cv.up_direction(one, wall), cv.up_direction(one), atol=1e-9)
    ring = np.stack([cv.look_at([np.cos(a), np.sin(a), 0.6], [0, 0, 0]) for a in np.linspace(0, 6, 8)])
    tilted = table @ np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]]).T
    assert np.allclose(cv.up_direction(ring, tilted), cv.up_direction(ring), atol=1e-9)   # the poses settle it


def test_depth_resolution_is_one_pixel_of_disparity_across_the_widest_baseline():
    """z^2 / (f B): f = 500 px, cameras 0.1 m apart at 1 m: 2 cm; a third camera nearer both does
    not change it, the farthest pair counts; one camera, or all at one place, resolve nothing (the
    depth itself); and never more than the depth."""
    from rg_core.geometry.conventions import depth_resolution

    K = np.array([[500.0, 0, 160], [0, 500.0, 120], [0, 0, 1]])
    poses = np.repeat(np.eye(4)[None], 3, 0)
    poses[1, 0, 3], poses[2, 0, 3] = 0.1, 0.05
    assert depth_resolution(np.stack([K] * 2), poses[:2], 1.0) == pytest.approx(0.02)
    assert depth_resolution(np.stack([K] * 3), poses, 1.0) == pytest.approx(0.02)
    assert depth_resolution(np.stack([K] * 3), poses, 2.0) == pytest.approx(0.08)
    assert depth_resolution(K[None], poses[:1], 1.5) == 1.5
    assert depth_resolution(np.stack([K] * 2), np.repeat(np.eye(4)[None], 2, 0), 1.5) == 1.5
    assert depth_resolution(np.stack([K] * 2), poses[:2], 1e4) == 1e4
    assert depth_resolution(np.stack([K] * 2), poses[:2], 0.0) == 0.0
