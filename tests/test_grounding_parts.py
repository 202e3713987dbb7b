"""Grounding building blocks: LERF relevancy, boxes, HDBSCAN grouping (subsample vs all)."""
import numpy as np
import pytest
import torch

from rg_core.grounding.boxes import box_iou_aabb, group_boxes, robust_inliers
from rg_core.grounding.grouping import cluster_instances, hdbscan_labels
from rg_core.grounding.relevancy import relevancy


def test_relevancy_matches_the_lerf_formula_and_saturates_safely():
    g = torch.Generator().manual_seed(0)
    f, q, c = torch.randn(50, 8, generator=g), torch.randn(8, generator=g), torch.randn(4, 8, generator=g)
    fn, qn, cn = (torch.nn.functional.normalize(t, dim=-1) for t in (f, q, c))
    want = torch.stack([min(torch.exp(x @ qn) / (torch.exp(x @ qn) + torch.exp(x @ ci)) for ci in cn) for x in fn])
    torch.testing.assert_close(relevancy(f, q, c), want)
    # Huge, tiny and zero features stay finite and in [0, 1].
    ext = torch.cat([f * 1e30, f * 1e-30, torch.zeros(1, 8)])
    r = relevancy(ext, q, c)
    assert torch.isfinite(r).all() and (r >= 0).all() and (r <= 1).all()
    # A feature equal to the query beats the canonical phrases.
    assert float(relevancy(q[None], q, c)[0]) > 0.5
    with pytest.raises(ValueError, match="one D"):
        relevancy(f, torch.randn(7), c)


def test_boxes_of_a_rotated_cuboid_and_degenerate_groups():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, (4000, 3)) * np.array([0.2, 0.05, 0.1])
    a = np.deg2rad(30)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    world = pts @ R.T + np.array([1.0, 2.0, 0.5])
    lo, hi, c, rot, ext = group_boxes(world)
    np.testing.assert_allclose(lo, world.min(0)), np.testing.assert_allclose(hi, world.max(0))
    np.testing.assert_allclose(c, [1.0, 2.0, 0.5], atol=0.02)
    np.testing.assert_allclose(sorted(ext), sorted([0.4, 0.1, 0.2]), atol=0.03)
    assert abs(np.linalg.det(rot) - 1) < 1e-6
    for degenerate in (world[:1], world[:3], np.c_[pts[:, :2], np.zeros(len(pts))]):
        out = group_boxes(degenerate)
        assert all(np.isfinite(v).all() for v in out)
    with pytest.raises(ValueError, match="finite points"):
        group_boxes(np.array([[0, 0, np.nan]]))
    assert box_iou_aabb([0, 0, 0], [1, 1, 1], [0, 0, 0], [1, 1, 1]) == 1.0
    assert box_iou_aabb([0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]) == 0.0
    assert abs(box_iou_aabb([0, 0, 0], [2, 1, 1], [1, 0, 0], [3, 1, 1]) - 1 / 3) < 1e-9
    # Stray points far away do not survive the robust filter.
    keep = robust_inliers(np.r_[world, [[50.0, 50.0, 50.0]]])
    assert keep[:-1].mean() > 0.99 and not keep[-1]


def _blobs(n_per: int, k: int, dim: int = 16, spread: float = 0.05, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    centres = torch.nn.functional.normalize(torch.randn(k, dim, generator=g), dim=-1)
    x = centres.repeat_interleave(n_per, 0) + spread * torch.randn(k * n_per, dim, generator=g)
    return torch.nn.functional.normalize(x, dim=-1), torch.arange(k).repeat_interleave(n_per)


def test_hdbscan_with_the_papers_parameters_finds_separated_groups():
    x, truth = _blobs(60, 5)
    labels = hdbscan_labels(x.numpy())
    from sklearn.metrics import adjusted_rand_score

    assert adjusted_rand_score(truth.numpy(), labels) > 0.95
    # Fewer points than min_cluster_size: everything is noise, never one forced cluster.
    assert (hdbscan_labels(x[:5].numpy()) == -1).all()


def test_clustering_a_subsample_agrees_with_clustering_all():
    from sklearn.metrics import adjusted_rand_score

    x, truth = _blobs(1500, 6, seed=3)
    full = cluster_instances(x, max_points=0)
    sub = cluster_instances(x, max_points=1500, seed=0)
    assert full.clustered == len(x) and sub.clustered == 1500
    agree = adjusted_rand_score(full.labels, sub.labels)
    assert agree > 0.95, agree
    assert adjusted_rand_score(truth.numpy(), sub.labels) > 0.95
    assert len(sub.centres) == 6
    torch.testing.assert_close(sub.centres.norm(dim=-1), torch.ones(6))
    # Outliers far from every group stay noise after assignment.
    far = torch.nn.functional.normalize(torch.randn(3, 16, generator=torch.Generator().manual_seed(9)), dim=-1)
    with_far = cluster_instances(torch.cat([x, -sub.centres[:1].repeat(3, 1) + 0 * far]), max_points=1500)
    assert (with_far.labels[-3:] == -1).all()


def test_cluster_instances_survives_nan_features():
    x, _ = _blobs(30, 3)
    x[0] = float("nan")
    out = cluster_instances(x, max_points=0)
    assert out.labels.shape == (90,) and torch.isfinite(out.centres).all()


def test_vocabulary_keeps_scene_names_and_drops_near_synonyms():
    from rg_core.grounding.vocabulary import build_vocabulary, looks_like_name

    base = {"phillips screwdriver": [1.0, 0.0, 0.0], "screwdriver": [0.95, 0.31, 0.0], "banana": [0.0, 0.0, 1.0],
            "apple": [0.0, 1.0, 0.0]}
    enc = lambda names: torch.tensor([base.get(n, [0.3, 0.3, 0.3]) for n in names])
    masks = enc(["screwdriver", "banana"])  # masks whose nearest household names are these two
    v = build_vocabulary(["phillips screwdriver"], ["apple"], masks, enc)
    assert v[:2] == ["phillips screwdriver", "apple"] and "banana" in v and "screwdriver" not in v
    assert looks_like_name("the red mug") and looks_like_name("orange")
    assert not looks_like_name("something to drink hot tea from") and not looks_like_name("")


def _camera_looking_down(x: float) -> np.ndarray:
    """cam_to_world [4, 4] (OpenCV axes) 1 m above (x, 0, 0), looking straight down at z = 0."""
    c2w = np.eye(4)
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])
    c2w[:3, 3] = [x, 0.0, 1.0]
    return c2w


def test_mask_votes_keep_an_objects_inside_that_views_from_around_it_bound():
    """A lemon's middle Gaussian lies behind its own surface in every view: views 40 degrees apart
    put it inside every silhouette within the object's width, so it stays; what lies 30 cm under
    the object, or inside it as seen from one direction only, goes."""
    from rg_core.geometry.conventions import look_at
    from rg_core.grounding.carve import MaskView, mask_votes

    K = np.array([[200.0, 0, 32], [0, 200.0, 32], [0, 0, 1]])
    v_, u_ = np.mgrid[0:64, 0:64]
    def view(eye):                        # a sphere of radius 4 cm at the origin on a far wall
        c2w = look_at(eye, [0, 0, 0])
        d = (np.stack([(u_ - 32) / 200.0, (v_ - 32) / 200.0, np.ones((64, 64))], -1) @ c2w[:3, :3].T)   # [64, 64, 3]
        o = c2w[:3, 3]
        b, c = d @ o, o @ o - 0.04 ** 2
        disc = b ** 2 - (d ** 2).sum(-1) * c
        t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (d ** 2).sum(-1), 0.0)
        return MaskView(K, c2w, np.where(disc > 0, t, 3.0), disc > 0)
    around = [view([np.sin(a), 0.0, np.cos(a)]) for a in np.radians([-40, 0, 40])]
    one = [view([0.01 * i, 0.0, 1.0]) for i in range(3)]
    pts = np.array([[0.0, 0.0, 0.0],       # its middle
                    [0.0, 0.0, -0.3],      # far behind it
                    [0.0, 0.0, 0.04]])     # on its surface, facing the middle view
    v = mask_votes(pts, around)
    np.testing.assert_array_equal(v.interior, [True, False, False])
    np.testing.assert_array_equal(v.carved(2), [False, True, False])
    w = mask_votes(pts, one)
    np.testing.assert_array_equal(w.interior, [False, False, False])
    np.testing.assert_array_equal(w.carved(2), [True, True, False])


def test_mask_votes_carve_what_views_see_elsewhere_and_keep_hidden_parts():
    from rg_core.grounding.carve import MaskView, mask_votes

    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    views = []
    for j, x in enumerate((-0.02, 0.0, 0.02)):
        c2w = _camera_looking_down(x)
        u0 = int(32 + 100 * (0.0 - x))            # the target: a 0.1 m patch of floor around x = 0
        m = np.zeros((64, 64), bool)
        m[27:38, u0 - 5:u0 + 6] = True
        depth = np.ones((64, 64))                 # a floor at z = 0, 1 m below every camera ...
        if j == 2:
            depth[30:35, u0 - 2:u0 + 3] = 0.5     # ... and in the last view an occluder over the target
        views.append(MaskView(K, c2w, depth, m))
    pts = np.array([[0.0, 0.0, 0.0],     # on the target: seen inside by two views, hidden in the third: kept
                    [0.2, 0.0, 0.0],     # on the floor elsewhere: seen outside by all
                    [0.0, 0.0, -0.3],    # 30 cm under a 10 cm target: no view sees it, no evidence it exists
                    [0.2, 0.0, -0.04],   # sunk 4 cm into the floor elsewhere: hidden, outside every silhouette
                    [0.2, 0.0, -0.01],   # 1 cm into the floor: within the 2 cm depth tolerance, seen outside
                    [5.0, 0.0, 0.0],     # off every image: no evidence, kept
                    [0.04, 0.0, -0.04]])  # 4 cm under it, hidden inside every silhouette, but all
    v = mask_votes(pts, views)              # from one direction: nothing tells it from what lies behind
    np.testing.assert_array_equal(v.inside, [2, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(v.outside, [0, 3, 0, 0, 3, 0, 0])
    np.testing.assert_array_equal(v.projected, [3, 0, 3, 0, 0, 0, 3])
    assert not v.interior.any()
    np.testing.assert_array_equal(v.carved(2), [False, True, True, True, True, False, True])
    np.testing.assert_array_equal(v.voted(2), [True, False, False, False, False, False, False])
    assert not v.voted(3)[0]
    # A Gaussian as large as its depth gap reaches the surface: seen.
    big = mask_votes(pts[3:4], views, sizes=np.array([0.025]))
    assert big.outside[0] == 3
    # A mask dilated by a pixel takes in the floor right beside the target.
    rim = np.array([[0.065, 0.0, 0.0]])
    assert mask_votes(rim, views).inside[0] == 0 and mask_votes(rim, views, border_px=1).inside[0] == 3
    with pytest.raises(ValueError, match="sizes must be"):
        mask_votes(pts, views, sizes=np.ones(2))


def test_sight_gives_pixels_and_visibility_and_marks_off_image_points():
    from rg_core.grounding.carve import sight

    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    depth = np.ones((64, 64))
    depth[56:64, 0:8] = 0.0                                 # a hole in the sensor depth (under the last point)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.3], [5.0, 0.0, 0.0], [-0.3, -0.3, 0.0]])
    c2w = np.stack([_camera_looking_down(0.0), _camera_looking_down(0.3)])        # [2, 4, 4]
    on, seen, r, u = sight(pts, np.stack([K, K]), c2w, [depth, np.ones((48, 64))], np.zeros(4))   # [2, 4] each
    np.testing.assert_array_equal(on[0], [True, True, False, True])
    np.testing.assert_array_equal(seen[0], [True, False, False, False])   # hidden below, off-image, in the hole
    assert (r[0, 2], u[0, 2]) == (-1, -1) and 0 <= r[0, 0] < 64 and 0 <= u[0, 0] < 64 and depth[r[0, 3], u[0, 3]] == 0.0
    # the second camera, 0.3 m along x over a smaller image, has the floor point 30 px further left
    assert u[1, 0] == u[0, 0] - 30 and r[1, 0] == r[0, 0]
    np.testing.assert_array_equal(seen[1], [True, False, False, False])   # the last one is off its 48 rows
    # a Gaussian as large as the gap to the surface reaches it
    assert sight(pts[1:2], K[None], c2w[:1], [depth], np.array([0.31]))[1][0, 0]


def _offline_mask_border(frames) -> int:
    """registration_border of the offline RGB-D masks on `frames` [(rgb, depth, K)], as vote_border measures it."""
    from rg_core.grounding.carve import mask_depth_offsets, registration_border
    from rg_core.perception.masks.rgbd import RGBDMaskGenerator

    gen, offs = RGBDMaskGenerator(), []
    for rgb, depth, K in frames:
        ms = [m.mask for m in gen.generate(rgb, depth, K) if 50 <= m.mask.sum() <= 0.5 * m.mask.size]
        offs.append(mask_depth_offsets(depth, ms))
    return registration_border(np.concatenate(offs))


def test_offline_masks_read_registered_on_renders_and_misregistered_on_a_real_sensor(synth_scene):
    """The votes grow masks only where colour and depth disagree: the offline masks of a synthetic
    render (registered by construction) give 0 px, those of YCB-Video 0002 at the map's 320 px
    (its colour is 2 px off its depth) give 1-3 px. A growth on renders put the table beside a
    fork or knife into its group (point -> object IoU 0.67 / 0.70 -> 0.82 / 0.84, seed 701)."""
    import cv2

    from conftest import need_rgbd
    from rg_core.io.captures import read_scene

    synth = [(f.load_rgb(), f.load_depth(), f.intrinsics.K) for f in synth_scene.train[::3]]
    assert _offline_mask_border(synth) == 0
    real = []
    for f in read_scene(need_rgbd("ycbv_0002_bop")).train[::6]:
        rgb, depth, K = f.load_rgb(), f.load_depth(), f.intrinsics.K.copy()
        s = 320 / rgb.shape[1]
        size = (320, round(rgb.shape[0] * s))
        K[:2] *= s
        real.append((cv2.resize(rgb, size, interpolation=cv2.INTER_AREA),
                     cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST), K))
    assert 1 <= _offline_mask_border(real) <= 3


def test_registration_border_measures_the_mask_to_depth_edge_offset():
    """A box standing 0.3 m out of a floor: its mask where the depth says it is gives 0 px; the same
    mask shifted by k px (colour and depth misregistered, as on a real RGB-D sensor) gives k px;
    a mask on a flat floor (a printed label) measures nothing."""
    from rg_core.grounding.carve import depth_edges, mask_depth_offsets, registration_border

    depth = np.full((80, 100), 1.0)
    depth[20:60, 30:70] = 0.7
    box = np.zeros_like(depth, bool)
    box[20:60, 30:70] = True
    assert depth_edges(depth).sum() > 0
    assert registration_border(mask_depth_offsets(depth, [box])) == 0
    for k in (1, 2, 3):
        shifted = np.roll(box, (k, k), axis=(0, 1))
        assert registration_border(mask_depth_offsets(depth, [shifted])) == k
    assert registration_border(mask_depth_offsets(depth, [np.roll(box, (4, 4), axis=(0, 1))]), max_px=3) == 3
    # a shift along one axis leaves the sides along it on their edges: half the boundary is on
    # the edge, which reads as registered
    assert registration_border(mask_depth_offsets(depth, [np.roll(box, (-2, 0), axis=(0, 1))])) == 0
    # registered: half the boundary on the edge, the rest 2-4 px off (an object on the table)
    assert registration_border(np.r_[np.zeros(60), np.full(60, 3.0)]) == 0
    # misregistered: few on the edge
    assert registration_border(np.r_[np.zeros(10), np.full(90, 2.2)]) == 2
    # the offline RGB-D masks on a synthetic render put about a quarter there (their part boundaries lie
    # near depth edges, not on them): still registered
    assert registration_border(np.r_[np.zeros(23), np.full(77, 1.0)]) == 0
    label = np.zeros_like(box)
    label[65:75, 10:25] = True
    assert len(mask_depth_offsets(depth, [label])) == 0 and registration_border(np.zeros(0)) == 0
    # unknown depth (0, NaN) makes no edges; too few measured pixels: no growth
    holes = depth.copy()
    holes[:, 50:] = np.nan
    holes[:5] = 0
    assert np.isfinite(mask_depth_offsets(holes, [box])).all()
    assert registration_border(np.ones(10), min_pixels=50) == 0
    with pytest.raises(ValueError, match="differ"):
        mask_depth_offsets(depth, [box[:10]])
    with pytest.raises(ValueError, match=r"\[h, w\]"):
        depth_edges(np.ones(5))


def test_nearest_is_exact_for_local_far_and_degenerate_queries():
    """geometry.points.nearest builds its tree over the queries' neighbourhood only; it must give the
    brute-force k nearest wherever the queries lie (inside the set, beyond its edge, everywhere)."""
    from rg_core.geometry.points import nearest

    rng = np.random.default_rng(3)
    pts = (rng.random((20000, 3)) * [4.0, 4.0, 1.0]).astype(np.float32)
    cases = {"local": [1.0, 1.0, 0.5] + rng.random((50, 3)) * 0.1,
             "beyond the edge": [9.0, 2.0, 0.5] + rng.random((5, 3)) * 0.1,
             "everywhere": rng.random((40, 3)) * [4.0, 4.0, 1.0],
             "on points": pts[:7].astype(np.float64)}
    for name, q in cases.items():
        d, idx = nearest(pts, q, 6)
        full = np.linalg.norm(q[:, None, :] - pts[None].astype(np.float64), axis=-1)    # [Q, N]
        want = np.sort(full, 1)[:, :6]
        np.testing.assert_allclose(d, want, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(np.take_along_axis(full, idx, 1), want, rtol=0, atol=1e-12, err_msg=name)
    d, idx = nearest(pts[:3], pts[:2], 8)                       # k above the set's size: all of it
    assert idx.shape == (2, 3) and d[:, 0].max() == 0.0
    assert nearest(pts[:0], pts[:2], 3)[1].shape == (2, 0) and nearest(pts, pts[:0], 3)[0].shape == (0, 3)


def test_within_matches_brute_force_for_tensors_arrays_and_edges():
    """geometry.points.within: the points a ball holds, the same for a tensor and an array, for an
    empty set, an empty ball and a centre far beyond float32's comfortable range."""
    import torch

    from rg_core.geometry.points import within

    rng = np.random.default_rng(5)
    pts = (rng.random((50000, 3)) * 4.0).astype(np.float32)
    c = np.array([1.0, 2.0, 0.5])
    want = np.nonzero(np.linalg.norm(pts.astype(np.float64) - c, axis=1) <= 0.7)[0]
    got = within(torch.from_numpy(pts), c, 0.7)
    assert 0 < len(want) < len(pts)
    # Points within float32 rounding of the sphere may land either side; none further off.
    assert len(np.setxor1d(got, want)) <= 2
    np.testing.assert_array_equal(got, within(pts, c, 0.7))
    assert np.all(np.diff(got) > 0)
    assert within(pts[:0], c, 1.0).shape == (0,) and within(pts, c, 0.0).shape == (0,)
    assert len(within(pts, [1e30, 0.0, 0.0], 1.0)) == 0 and len(within(pts, c, 1e30)) == len(pts)


def test_connected_to_keeps_the_anchor_piece():
    from rg_core.geometry.points import map_spacing
    from rg_core.grounding.boxes import connected_to

    rng = np.random.default_rng(0)
    a = rng.uniform(0, 0.05, (200, 3))                 # dense piece at the origin
    b = rng.uniform(0, 0.05, (300, 3)) + [1.0, 0, 0]    # a larger one 1 m away
    pts = np.concatenate([a, b])
    link = 3 * map_spacing(pts)
    assert 0 < link < 0.1
    keep = connected_to(pts, np.array([0.0, 0.0, 0.0]), link)
    assert keep[:200].all() and not keep[200:].any()
    keep = connected_to(pts, None, link)
    assert keep[200:].all() and not keep[:200].any()
    assert connected_to(pts[:1], None, link).all() and connected_to(pts, None, 0.0).all()


def test_connected_to_prefers_the_piece_the_mask_supports():
    """ycbv_0002's large marker: the peak pixel's anchor fell on 6 Gaussians of the table behind the
    marker's cap (in its mask, with the table's depth); the body, which the mask sees, was dropped."""
    from rg_core.geometry.points import map_spacing
    from rg_core.grounding.boxes import connected_to

    rng = np.random.default_rng(1)
    body = rng.uniform(0, 0.02, (150, 3)) * [1, 6, 1]          # a thin upright object
    stray = rng.uniform(0, 0.01, (6, 3)) + [0, 0, 0.11]        # 11 cm behind: the background
    pts = np.concatenate([body, stray])
    link = 3 * map_spacing(pts)
    support = np.zeros(len(pts), bool)
    support[:120] = True                                        # seen inside the reference mask
    support[-6:] = True
    anchor = stray.mean(0)
    assert connected_to(pts, anchor, link)[-6:].all()           # the anchor alone: the stray piece
    keep = connected_to(pts, anchor, link, support)
    assert keep[:150].all() and not keep[150:].any()
    # No support anywhere: the anchor's piece, as before.
    assert (connected_to(pts, anchor, link, np.zeros(len(pts), bool)) == connected_to(pts, anchor, link)).all()
    with pytest.raises(ValueError):
        connected_to(pts, anchor, link, support[:-1])


def test_connected_to_keeps_every_piece_the_mask_sees():
    """ycb_video_3's mug: no depth at the rim split its front wall from its inside at the link
    distance, and only the inside was kept (visible IoU 0.39). A second piece the reference mask
    sees is kept too, unless the mask sees it less than it sees it outside (the table) or it is
    small next to the kept one (a few background Gaussians behind a thin object's edge)."""
    from rg_core.geometry.points import map_spacing
    from rg_core.grounding.boxes import connected_to

    rng = np.random.default_rng(2)
    inside = rng.uniform(0, 0.04, (300, 3))                     # the mug's inside
    front = rng.uniform(0, 0.04, (200, 3)) + [0, 0.06, 0]       # its front wall, 2 cm apart
    table = rng.uniform(0, 0.04, (150, 3)) + [0, -0.06, 0]      # seen outside the mask
    stray = rng.uniform(0, 0.01, (6, 3)) + [0, 0, 0.11]         # background behind an edge, in the mask
    pts = np.concatenate([inside, front, table, stray])
    link = 3 * map_spacing(pts)
    assert link < 0.02
    support = np.zeros(len(pts), bool)
    against = np.zeros(len(pts), bool)
    support[:500] = True
    support[500:520] = True                                     # the table's edge bleeds into the mask
    against[520:650] = True
    support[-6:] = True
    keep = connected_to(pts, None, link, support, against)
    assert keep[:500].all() and not keep[500:].any()
    # Without `against`, as before: the most supported piece alone.
    only = connected_to(pts, None, link, support)
    assert only[:300].all() and not only[300:].any()
    # A second piece below `also_share` of the kept one's support is dropped.
    assert not connected_to(pts, None, link, support, against, also_share=0.7)[300:500].any()
    with pytest.raises(ValueError):
        connected_to(pts, None, link, support, against[:-1])


def test_relevancy_in_pca_space_matches_decompressing_first():
    from rg_core.grounding.relevancy import relevancy_pca
    from rg_core.perception.pca import PCA

    g = torch.Generator().manual_seed(3)
    x = torch.randn(200, 48, generator=g) + 2.0                 # embeddings with a mean away from 0
    for k in (16, 64):                                          # 64 > rank: zero-padded components
        pca = PCA.fit(x[:40], k)
        z = torch.randn(7, 9, pca.dim, generator=g)             # [h, w, k] codes, any values
        q, c = torch.randn(48, generator=g), torch.randn(4, 48, generator=g)
        want = relevancy(pca.inverse(z), q, c)
        torch.testing.assert_close(relevancy_pca(z, pca.components, pca.mean, q, c), want, atol=1e-5, rtol=1e-5)
    # The code of the mean (decompresses to the mean exactly) and huge codes stay finite in [0, 1].
    ext = torch.cat([torch.zeros(1, pca.dim), torch.full((1, pca.dim), 1e30)])
    r = relevancy_pca(ext, pca.components, pca.mean, q, c)
    assert torch.isfinite(r).all() and (r >= 0).all() and (r <= 1).all()
    with pytest.raises(ValueError, match="relevancy_pca"):
        relevancy_pca(z[..., :3], pca.components, pca.mean, q, c)


def test_hdbscan_merges_micro_clusters_below_epsilon():
    """Tight micro-clusters inside clusters: scikit-learn <= 1.9.1 with NumPy >= 2.4 raises a
    TypeError in its epsilon search (scikit-learn #33219); hdbscan_labels must still return the
    clusters that epsilon 0.01 defines: each pair of micro-clusters 0.006 apart is one group."""
    rng = np.random.default_rng(0)
    e = np.eye(8)
    centres = (e[0], e[0] + 0.002, e[1], e[1] + 0.002, e[2])
    x = np.concatenate([c + 3e-4 * rng.standard_normal((15, 8)) for c in centres])
    truth = np.repeat([0, 0, 1, 1, 2], 15)
    lab = hdbscan_labels(x, 10, 0.01)
    assert (lab >= 0).all() and len(np.unique(lab)) == 3
    for t in range(3):
        assert len(np.unique(lab[truth == t])) == 1
    # Without epsilon the micro-clusters stay apart.
    assert len(np.unique(hdbscan_labels(x, 10, 0.0))) >= 4


def test_merge_closer_than_joins_touching_clusters_and_keeps_noise():
    from rg_core.grounding.grouping import merge_closer_than

    x = np.array([[0.0], [0.05], [0.5], [0.52], [3.0], [9.0]])
    lab = np.array([0, 0, 1, 1, 2, -1])
    np.testing.assert_array_equal(merge_closer_than(x, lab, 0.01), [0, 0, 1, 1, 2, -1])
    out = merge_closer_than(x, np.array([0, 1, 2, 2, -1, -1]), 0.06)   # 0 and 1 touch at 0.05
    assert out[0] == out[1] != out[2] == out[3] and (out[4:] == -1).all()
    np.testing.assert_array_equal(merge_closer_than(x, np.full(6, -1), 0.1), np.full(6, -1))


def test_groups_ball_and_nearest_pick_gaussians_by_feature():
    """A query feature in no cluster: ball() takes the Gaussians within the median cluster radius,
    nearest() the k most similar ones (sorted Gaussian ids of a region's rows) and their mean similarity."""
    from rg_core.grounding.grouping import Groups

    f = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0], [0.9, 0.1], [0.0, 1.0], [-1.0, 0.0]]), dim=-1)
    g = Groups(labels=np.array([0, 0, -1, -1]), centres=f[:1], clustered=4, seconds=0.0,
               radius=torch.tensor([0.01]), features=f, ids=np.array([40, 10, 30, 20]))
    assert g.ball(torch.tensor([2.0, 0.0])).tolist() == [40, 10]          # cosine distance <= 0.01 (0.0061 for row 1)
    assert g.ball(torch.tensor([0.0, 1.0]), radius=0.5).tolist() == [30]
    ids, sim = g.nearest(torch.tensor([1.0, 0.2]), 2)
    assert ids.tolist() == [10, 40] and 0.95 < sim <= 1.0
    ids, _ = g.nearest(torch.tensor([1.0, 0.0]), 10)                        # k above the rows: all of them
    assert ids.tolist() == [10, 20, 30, 40]
    assert Groups(labels=np.zeros(0, np.int64), centres=f[:0], clustered=0, seconds=0.0).ball(f[0]).size == 0


def test_mask_points_thinned_are_a_stride_of_all_and_skip_missing_depth():
    from rg_core.grounding.stages import mask_points
    from rg_core.map.keyframes import Keyframe

    h, w = 40, 50
    depth = torch.full((h, w), 2.0)
    depth[5:10, :] = 0.0                          # no reading: never a point
    K = np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]])
    kf = Keyframe(0, 0.0, np.eye(4), K, torch.zeros(h, w, 3), depth)
    mask = np.zeros((h, w), bool)
    mask[:30, 10:40] = True
    full = mask_points(kf, mask)
    assert len(full) == 25 * 30 and np.allclose(full[:, 2], 2.0)
    thin = mask_points(kf, mask, at_most=100)
    assert 100 <= len(thin) <= 200                 # "at most about twice that"
    np.testing.assert_array_equal(thin, full[:: len(full) // 100])
    np.testing.assert_array_equal(mask_points(kf, mask, at_most=10_000), full)
    assert mask_points(kf, np.zeros((h, w), bool), at_most=5).shape == (0, 3)
