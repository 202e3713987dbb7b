"""Visible masks sharpened by the camera's depth image (rg_core.grounding.masks.refine_visible),
rid of occluders the map renders too thin (leave_occluded) and snapped to its colour image's edges
(snap_to_image)."""
import numpy as np
import pytest

from rg_core.grounding.masks import leave_occluded, refine_visible, snap_to_image, surfaces_apart

H, W = 24, 32


def _square_scene():
    """An object (rows 8-15, cols 10-19) at 1.0 m before a wall at 2.0 m; the map renders it one
    pixel to the right (cols 11-20), its Gaussians spreading over cols 9-21 alone; the rest of the
    map (the wall) covers every pixel at 2.0 m."""
    truth = np.zeros((H, W), bool)
    truth[8:16, 10:20] = True
    depth = np.where(truth, 1.0, 2.0).astype(np.float32)
    rendered = np.zeros((H, W), bool)
    rendered[8:16, 11:21] = True
    ga = np.zeros((H, W), np.float32)
    ga[7:17, 9:22] = 0.9
    gd = np.where(ga > 0, 1.0, 0.0).astype(np.float32)
    return truth, depth, rendered, (ga, gd, np.ones((H, W), np.float32), np.full((H, W), 2.0, np.float32))


def test_a_shifted_render_is_moved_onto_the_sensed_object():
    truth, depth, rendered, surf = _square_scene()
    out = refine_visible(rendered, *surf, depth, rel_tol=0.03)
    np.testing.assert_array_equal(out, truth)           # col 20 (the wall) out, col 10 (the object) in


def test_an_occluder_the_map_holds_removes_its_pixels():
    truth, depth, _, (ga, gd, ra, rd) = _square_scene()
    depth[8:16, 10:15] = rd[8:16, 10:15] = 0.6          # a box in front of the left half, in the map
    out = refine_visible(truth, ga, gd, ra, rd, depth, rel_tol=0.03)
    assert not out[:, :15].any() and out[8:16, 15:20].all()


def test_rim_pixels_join_only_where_the_group_covers_them():
    """Col 10 holds the object, but the group barely reaches it and the rest of the map (another
    group's Gaussians) renders that same surface: depth cannot decide, col 10 stays out."""
    truth, depth, rendered, (ga, gd, ra, rd) = _square_scene()
    ga[:, 10] = 0.05                                    # the group barely reaches col 10
    rd[:, 10] = 1.0                                     # ... and the rest holds its surface
    out = refine_visible(rendered, ga, gd, ra, rd, depth, rel_tol=0.03)
    assert not out[:, 10].any() and not out[:, 20].any()


def test_an_unmapped_rim_that_continues_the_object_joins():
    """The map holds nothing of col 10 but the wall behind it (the group missed the object's rim): its
    readings lie in front of the wall and continue the mask's, so it joins; rows where something
    unmapped stands far in front (0.5 m, not continuing the object) stay out, as does col 9 (the wall,
    not touching the mask)."""
    truth, depth, rendered, (ga, gd, ra, rd) = _square_scene()
    ga[:, 9:11] = 0.0
    out = refine_visible(rendered, ga, gd, ra, rd, depth, rel_tol=0.03)
    np.testing.assert_array_equal(out, truth)
    depth[8:12, 10] = 0.5                               # an unmapped occluder before the rim
    out = refine_visible(rendered, ga, gd, ra, rd, depth, rel_tol=0.03)
    assert not out[8:12, 10].any() and out[12:16, 10].all() and not out[:, 9].any()


def test_an_unmapped_rim_two_pixels_wide_joins_and_a_third_pixel_does_not():
    """The map holds nothing of cols 10-12 (the mapper seeds one Gaussian per 2x2 block, so a rim it
    missed can be two pixels wide): readings continuing the object join out to `rim_px` pixels from
    the mask, one pixel with rim_px=1, none with 0."""
    truth, depth, rendered, (ga, gd, ra, rd) = _square_scene()
    truth[8:16, 9] = True                               # the object is one column wider on the left
    depth[truth] = 1.0
    rendered = truth.copy()
    rendered[:, 9:13] = False                           # the map renders cols 13-19 ...
    ga[:, 7:13] = 0.0                                   # ... and holds nothing left of them
    for rim_px, first in ((2, 11), (1, 12), (0, 13)):
        out = refine_visible(rendered, ga, gd, ra, rd, depth, rel_tol=0.03, rim_px=rim_px)
        expect = truth.copy()
        expect[:, :first] = False
        np.testing.assert_array_equal(out, expect)


def test_surfaces_too_close_to_tell_apart_keep_the_rendered_answer():
    """The object's foot on a table 2 cm behind it: at 3 % of 1-2 m the two cannot be told apart by
    depth; at 1 % (floor 1 cm) they can."""
    truth, depth, rendered, (ga, gd, ra, rd) = _square_scene()
    rd[:] = 1.02
    depth[~truth] = 1.02
    np.testing.assert_array_equal(refine_visible(rendered, ga, gd, ra, rd, depth, rel_tol=0.03), rendered)
    np.testing.assert_array_equal(refine_visible(rendered, ga, gd, ra, rd, depth, rel_tol=0.01), truth)


@pytest.mark.parametrize("bad", [0.0, np.nan, np.inf, -np.inf, -1.0])
def test_pixels_without_a_reading_keep_the_rendered_answer(bad):
    _, _, rendered, surf = _square_scene()
    depth = np.full((H, W), bad, np.float32)
    np.testing.assert_array_equal(refine_visible(rendered, *surf, depth, rel_tol=0.03), rendered)


@pytest.mark.parametrize("extreme, empty", [(1e-30, False), (3.0e38, True), (1e300, True)])
def test_extreme_depths_go_to_the_nearer_surface_without_overflow(extreme, empty):
    _, _, rendered, surf = _square_scene()
    with np.errstate(all="raise"):                      # no overflow, no invalid operation
        out = refine_visible(rendered, *surf, np.full((H, W), extreme), rel_tol=0.03)
    assert not out.any() if empty else (out >= rendered).all()


def test_a_group_without_a_finite_rendered_depth_keeps_the_rendered_answer():
    _, depth, rendered, (ga, gd, ra, rd) = _square_scene()
    gd[:] = np.nan
    np.testing.assert_array_equal(refine_visible(rendered, ga, gd, ra, rd, depth, rel_tol=0.03), rendered)


def test_a_depth_image_of_another_size_is_a_clear_error():
    _, _, rendered, surf = _square_scene()
    with pytest.raises(ValueError, match=r"depth image is 16x12 but the mask is 32x24"):
        refine_visible(rendered, *surf, np.ones((12, 16), np.float32), rel_tol=0.03)


K_CAM = np.array([[20.0, 0.0, 16.0], [0.0, 20.0, 12.0], [0.0, 0.0, 1.0]])


def _splats(rows, cols, z, scale):
    """One round Gaussian on each pixel's ray at depth z (camera = world frame)."""
    v, u = np.meshgrid(np.arange(*rows), np.arange(*cols), indexing="ij")
    pts = np.stack([(u - 16.0) * z / 20.0, (v - 12.0) * z / 20.0, np.full(u.shape, z)], -1).reshape(-1, 3)
    return pts, np.full((len(pts), 3), scale)


def _occluded_scene(occluder_z=0.8):
    """The group: a plate of Gaussians at 1.0 m on rows 8-15, cols 10-19, rendered there with alpha
    0.9; a thin occluder of the rest's Gaussians at occluder_z before cols 10-13, which the sensor
    sees; the mask (as rendered) holds the whole plate."""
    gp, gs = _splats((8, 16), (10, 20), 1.0, 0.03)
    op, os_ = _splats((8, 16), (10, 14), occluder_z, 0.03)
    means, scales = np.r_[gp, op], np.r_[gs, os_]
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (len(means), 1))
    member = np.r_[np.ones(len(gp), bool), np.zeros(len(op), bool)]
    mask = np.zeros((H, W), bool)
    mask[8:16, 10:20] = True
    depth = np.where(mask, 1.0, 2.0)
    depth[8:16, 10:14] = occluder_z
    ga = np.where(mask, 0.9, 0.0)
    gd = np.where(mask, 1.0, 0.0)
    return mask, depth, ga, gd, (means, scales, quats, np.full(len(means), 0.9)), member


def test_a_thin_occluder_the_rest_holds_leaves_the_mask():
    mask, depth, ga, gd, gs, member = _occluded_scene()
    out = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), gs, member, rel_tol=0.03)
    expect = mask.copy()
    expect[8:16, 10:14] = False
    np.testing.assert_array_equal(out, expect)


def test_readings_in_front_that_the_group_holds_or_nothing_holds_stay():
    """The group's own Gaussians at the reading (its rendered depth lies behind them), an unmapped
    occluder (no Gaussian near the reading) and one within the tolerance all keep the mask."""
    mask, depth, ga, gd, (means, scales, quats, op), member = _occluded_scene()
    out = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), (means, scales, quats, op), ~member, rel_tol=0.03)
    np.testing.assert_array_equal(out, mask)            # the plate behind is the rest, the occluder the group
    keep = np.ones(len(means), bool)
    keep[member.sum():] = False                         # the occluder is not in the map at all
    out = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), tuple(t[keep] for t in (means, scales, quats, op)),
                         member[keep], rel_tol=0.03)
    np.testing.assert_array_equal(out, mask)
    mask2, depth2, ga2, gd2, gs2, member2 = _occluded_scene(occluder_z=0.985)
    out = leave_occluded(mask2, depth2, ga2, gd2, K_CAM, np.eye(4), gs2, member2, rel_tol=0.03)
    np.testing.assert_array_equal(out, mask2)           # 1.5 cm in front: within max(1 cm, 3 %)


def _smeared_scene():
    """The group: a plate of Gaussians at 1.0 m on rows 8-15, cols 10-19, before a wall of the rest's
    Gaussians at 2.0 m over the whole image. The mask (as rendered) smears two columns past the
    plate's right edge (cols 20-21), where the sensor sees the wall behind it."""
    gp, gs = _splats((8, 16), (10, 20), 1.0, 0.03)
    wp, ws = _splats((0, H), (0, W), 2.0, 0.03)
    means, scales = np.r_[gp, wp], np.r_[gs, ws]
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (len(means), 1))
    member = np.r_[np.ones(len(gp), bool), np.zeros(len(wp), bool)]
    mask = np.zeros((H, W), bool)
    mask[8:16, 10:22] = True
    depth = np.full((H, W), 2.0)
    depth[8:16, 10:20] = 1.0
    ga = np.where(mask, 0.9, 0.0)
    ga[:, 20:22] *= 0.4
    gd = np.where(mask, 1.0, 0.0)
    return mask, depth, ga, gd, (means, scales, quats, np.full(len(means), 0.9)), member


def test_a_rim_smeared_over_the_wall_behind_leaves_the_mask():
    """The smear's readings lie behind the group's surface, so only the rim rule can see them: the
    wall's Gaussians hold those 3D points, the plate's own rim (its Gaussians hold it) stays."""
    mask, depth, ga, gd, gs, member = _smeared_scene()
    expect = mask.copy()
    expect[:, 20:22] = False
    out = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), gs, member, rel_tol=0.03, rim_ratio=4.0)
    np.testing.assert_array_equal(out, expect)
    old = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), gs, member, rel_tol=0.03)
    np.testing.assert_array_equal(old, mask)                    # rim_ratio 0: the smear stays
    where = np.ones((H, W), bool)
    where[:, 21] = False                                        # e.g. surfaces too close to tell apart
    out = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), gs, member, rel_tol=0.03, rim_ratio=4.0,
                         rim_where=where)
    expect[:, 21] = mask[:, 21]
    np.testing.assert_array_equal(out, expect)


def test_surfaces_apart_tells_a_flat_object_from_a_cup_before_a_wall():
    """A flat object 5 mm over the table cannot be told apart at 1 m; a cup 1 m before a wall can,
    and so can a group with nothing of the rest behind it; no group there: nothing to tell."""
    ga = np.array([[0.9, 0.9, 0.9, 0.0]])
    gd = np.array([[1.0, 1.0, 1.0, 0.0]])
    ra = np.array([[0.9, 0.9, 0.0, 0.9]])
    rd = np.array([[1.005, 2.0, 0.0, 2.0]])
    np.testing.assert_array_equal(surfaces_apart(ga, gd, ra, rd, rel_tol=0.015), [[False, True, True, False]])


@pytest.mark.parametrize("case", ["nan_depth", "zero_scales", "huge_scales", "tiny_opacity", "no_gaussians"])
def test_degenerate_readings_and_gaussians_give_a_mask_not_an_error(case):
    mask, depth, ga, gd, (means, scales, quats, op), member = _occluded_scene()
    if case == "nan_depth":
        depth[8:12] = np.nan
        depth[12:14] = np.inf
        depth[14:16] = 0.0
    elif case == "zero_scales":
        scales = np.zeros_like(scales)
    elif case == "huge_scales":
        scales = np.full_like(scales, 1e30)
    elif case == "tiny_opacity":
        op = np.full_like(op, 1e-30)
    else:
        means, scales, quats, op, member = means[:0], scales[:0], quats[:0], op[:0], member[:0]
    out = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), (means, scales, quats, op), member, rel_tol=0.03)
    assert out.shape == mask.shape and out.dtype == bool and not (out & ~mask).any()
    if case == "nan_depth":
        np.testing.assert_array_equal(out, mask)        # no reading: nothing to decide
    if case == "huge_scales":
        np.testing.assert_array_equal(out[:, 14:], mask[:, 14:])
    rim = leave_occluded(mask, depth, ga, gd, K_CAM, np.eye(4), (means, scales, quats, op), member, rel_tol=0.03,
                         rim_ratio=4.0)
    assert rim.shape == mask.shape and rim.dtype == bool and not (rim & ~mask).any()
    if case == "nan_depth":
        np.testing.assert_array_equal(rim, mask)
    with pytest.raises(ValueError, match="depth image is 5x4 but the mask is 32x24"):
        leave_occluded(mask, np.ones((4, 5)), ga, gd, K_CAM, np.eye(4), (means, scales, quats, op), member, 0.03)


def _coloured(truth: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8: a red object on a grey wall with some texture (+-10 levels)."""
    rng = np.random.default_rng(0)
    img = np.where(truth[..., None], np.array([200, 40, 30]), np.array([120, 120, 120])) + rng.integers(-10, 11, (H, W, 3))
    return img.astype(np.uint8)


def test_a_ragged_rim_snaps_to_the_colour_edge():
    """The map's silhouette a pixel off here and there (every other row: the object's last column out,
    the wall's next column in, and a wall pixel of the top row in) comes back onto the object; uint8
    and float [0, 1] images give the same answer, and a right mask stays."""
    truth, _, _, _ = _square_scene()
    ragged = truth.copy()
    ragged[8:16:2, 19] = False
    ragged[9:16:2, 20] = True
    ragged[7, 14] = True
    img = _coloured(truth)
    np.testing.assert_array_equal(snap_to_image(ragged, img), truth)
    np.testing.assert_array_equal(snap_to_image(ragged, img.astype(np.float32) / 255), truth)
    np.testing.assert_array_equal(snap_to_image(truth, img), truth)


def test_a_thin_object_missing_half_its_width_gets_it_back_from_the_colour():
    """A red bar two pixels wide (rows 10-11) whose mask holds only row 10 over cols 8-23: the guided
    filter's 3x3 window sees as much wall as bar around row 11 and leaves it out; each rim pixel then
    takes the side whose colour within 2 px is nearer, so row 11 joins and no wall pixel does. With
    a margin no colour difference can reach (2 > sqrt(3)), nothing moves."""
    truth = np.zeros((H, W), bool)
    truth[10:12, 6:26] = True
    mask = truth.copy()
    mask[11, 8:24] = False
    img = _coloured(truth)
    np.testing.assert_array_equal(snap_to_image(mask, img), truth)
    assert not snap_to_image(mask, img, margin=2.0)[11, 8:24].all()


def test_without_a_colour_edge_the_mask_only_smooths():
    """A flat image holds no edge to snap to: a square mask keeps its interior and does not grow."""
    truth, _, _, _ = _square_scene()
    out = snap_to_image(truth, np.full((H, W, 3), 90, np.uint8))
    assert not (out & ~truth).any() and out[9:15, 11:19].all()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e30, -1e30])
def test_non_finite_and_extreme_colours_give_a_mask_not_an_error(bad):
    truth, _, _, _ = _square_scene()
    img = _coloured(truth).astype(np.float32) / 255
    img[0:4] = bad                                        # rows far from the object
    np.testing.assert_array_equal(snap_to_image(truth, img), truth)


def test_an_empty_mask_or_eps_0_is_returned_as_is_and_a_wrong_image_is_a_clear_error():
    truth, _, rendered, _ = _square_scene()
    img = _coloured(truth)
    assert not snap_to_image(np.zeros((H, W), bool), img).any()
    np.testing.assert_array_equal(snap_to_image(rendered, img, eps=0.0), rendered)
    with pytest.raises(ValueError, match=r"colour image is \[24, 32\] but the mask is 32x24"):
        snap_to_image(rendered, img[..., 0])
    with pytest.raises(ValueError, match=r"colour image is \[12, 16, 3\] but the mask is 32x24"):
        snap_to_image(rendered, img[::2, ::2])
