"""Depth normals and the concave-seam split of a point answer (grounding.parts)."""
import numpy as np
import pytest
import torch

from rg_core.geometry.normals import depth_normals, organised_normals
from rg_core.grounding.carve import MaskVotes
from rg_core.grounding.parts import MIN_PART, concave_parts, part_at, polished, seam_graph, seen_normals


def box_surface(lo, hi, h, others=(), rng=None, jitter_deg=0.0):
    """Points [n, 3] on the faces of box lo..hi (spacing h, no bottom: it rests on z = lo[2]) with
    their outward normals [n, 3]; points inside or on another box of `others` are its contact face."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pts, nrm = [], []
    for ax in range(3):
        for side, val in ((-1, lo[ax]), (1, hi[ax])):
            if ax == 2 and side == -1:
                continue
            o = [a for a in range(3) if a != ax]
            g = [np.arange(lo[a] + h / 2, hi[a], h) for a in o]
            A, B = np.meshgrid(*g, indexing="ij")
            p = np.zeros((A.size, 3))
            p[:, o[0]], p[:, o[1]], p[:, ax] = A.ravel(), B.ravel(), val
            n = np.zeros_like(p)
            n[:, ax] = side
            pts.append(p), nrm.append(n)
    pts, nrm = np.concatenate(pts), np.concatenate(nrm)
    for olo, ohi in others:
        inside = ((pts >= np.asarray(olo) - h / 2) & (pts <= np.asarray(ohi) + h / 2)).all(1)
        pts, nrm = pts[~inside], nrm[~inside]
    if jitter_deg and rng is not None:
        nrm = nrm + rng.normal(0, np.radians(jitter_deg), nrm.shape)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return pts, nrm


def two_boxes(jitter_deg=0.0):
    rng = np.random.default_rng(0)
    A, B = ((0, 0, 0), (0.1, 0.1, 0.1)), ((0.1, 0.02, 0), (0.2, 0.08, 0.06))
    pa, na = box_surface(*A, 0.008, [B], rng, jitter_deg)
    pb, nb = box_surface(*B, 0.008, [A], rng, jitter_deg)
    return np.concatenate([pa, pb]), np.concatenate([na, nb]), np.r_[np.zeros(len(pa), int), np.ones(len(pb), int)]


@pytest.mark.parametrize("jitter", [0.0, 8.0])
def test_two_touching_boxes_split_at_their_concave_seam(jitter):
    pts, nrm, truth = two_boxes(jitter)
    label = concave_parts(pts, nrm)
    assert len(np.unique(label)) == 2
    agree = max(np.mean(label == truth), np.mean(label != truth))
    assert agree >= 0.97, agree
    for i, click in enumerate([(0.05, 0.05, 0.1), (0.15, 0.05, 0.06)]):   # each box's top
        keep = part_at(pts, nrm, np.array(click))
        assert np.mean(truth[keep] == i) >= 0.97 and keep[truth == i].mean() >= 0.95


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_the_split_does_not_depend_on_the_units(scale):
    """Millimetre crumbs or a warehouse's boxes, float32 or float64: the same parts."""
    pts, nrm, truth = two_boxes(4.0)
    want = concave_parts(pts, nrm)
    got = concave_parts((pts * scale).astype(np.float32), nrm.astype(np.float32))
    assert max(np.mean(got == want), np.mean(got != want)) >= 0.99


def sphere(r, n, rng):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return r * v, v


def cylinder(r, length, h):
    t, z = np.meshgrid(np.arange(0, 2 * np.pi, h / r), np.arange(0, length, h), indexing="ij")
    n = np.stack([np.cos(t), np.sin(t), 0 * t], -1).reshape(-1, 3)
    return n * r + np.c_[0 * z.ravel(), 0 * z.ravel(), z.ravel()], n


@pytest.mark.parametrize("shape", ["box", "sphere", "marker", "flat"])
def test_one_convex_object_stays_whole(shape):
    rng = np.random.default_rng(1)
    if shape == "box":
        pts, nrm = box_surface((0, 0, 0), (0.12, 0.05, 0.2), 0.008)
    elif shape == "sphere":
        pts, nrm = sphere(0.04, 800, rng)
    elif shape == "marker":   # long and thin: a normalized cut would halve it, the seam rule does not
        pts, nrm = cylinder(0.01, 0.13, 0.003)
    else:                     # a flat sheet, normals noisy
        pts = np.c_[rng.uniform(0, 0.2, (600, 2)), np.zeros(600)]
        nrm = np.c_[rng.normal(0, 0.1, (600, 2)), np.ones(600)]
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    assert len(np.unique(concave_parts(pts, nrm))) == 1


def test_degenerate_inputs_keep_the_group_whole():
    pts, nrm, _ = two_boxes()
    assert (concave_parts(pts, np.zeros_like(nrm)) == 0).all()          # no normal known: nothing to cut at
    few = pts[: 2 * MIN_PART - 1]
    assert (concave_parts(few, nrm[: len(few)]) == 0).all()
    same = np.zeros((100, 3))                                             # every point in one place
    assert len(np.unique(concave_parts(same, np.tile([0, 0, 1.0], (100, 1))))) == 1
    bad = nrm.copy()
    bad[::7] = np.nan                                                      # NaN normals are unknown ones
    label = concave_parts(pts, np.nan_to_num(bad))
    assert label.shape == (len(pts),) and (label >= 0).all()
    # two pieces far apart, one too small to stand alone: it joins its nearest part
    far = np.r_[pts, pts[:5] + 1.0]
    label = concave_parts(far, np.r_[nrm, nrm[:5]])
    assert len(np.unique(label)) == 2


def test_depth_normals_of_a_tilted_plane_face_the_camera_and_skip_missing_depth():
    K = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(128), np.arange(96))
    n_true = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])   # towards the camera
    ray = np.stack([(u - 64) / 100.0, (v - 48) / 100.0, np.ones_like(u, float)], -1)
    depth = (-1.0 / (ray @ n_true)).astype(np.float32)                         # plane n . x = 1
    depth[10, 10], depth[20, 30], depth[30, 40] = 0.0, np.nan, np.inf
    for step, med in ((1, 0), (4, 5)):
        n = depth_normals(depth, K, step, med)
        assert np.isfinite(n).all()
        ok = np.linalg.norm(n, axis=-1) > 0
        assert not ok[10, 10] and not ok[20, 30] and not ok[30, 40]
        assert ok.mean() > 0.6
        away = np.ones_like(ok)                            # 7 px from a hole: step + median window, all readings
        for r, c in ((10, 10), (20, 30), (30, 40)):
            away[r - 7:r + 8, c - 7:c + 8] = False
        assert np.allclose(n[ok & away], n_true, atol=1e-3)
        assert (n[ok] @ n_true).min() > np.cos(np.radians(5))
    assert not np.linalg.norm(depth_normals(depth, K, 1)[10, 11], axis=-1) > 0      # a neighbour lacks depth
    for scale in (1e-4, 1e4):                                                    # tiny and huge depths
        n = depth_normals(depth * scale, K, 2)
        assert np.isfinite(n).all() and np.allclose(n[np.linalg.norm(n, axis=-1) > 0], n_true, atol=1e-3)
    assert not depth_normals(np.zeros((8, 8)), K).any()
    with pytest.raises(ValueError, match=r"\[H, W\]"):
        depth_normals(np.zeros(8), K)
    with pytest.raises(ValueError, match="median_px"):
        depth_normals(depth, K, 1, 4)
    rr, cc = np.array([0, 10, 11, 50, 50]), np.array([0, 10, 10, 60, 61])         # a few pixels: as the image's
    np.testing.assert_allclose(depth_normals(depth, K, 4, 5, (rr, cc)), depth_normals(depth, K, 4, 5)[rr, cc])


def test_organised_normals_at_step_one_are_the_cross_of_central_differences():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(6, 7, 3))
    valid = rng.random((6, 7)) > 0.2
    n = organised_normals(pts, valid)
    c = np.cross(pts[2:, 1:-1] - pts[:-2, 1:-1], pts[1:-1, 2:] - pts[1:-1, :-2])   # dy x dx
    want = -c / np.linalg.norm(c, axis=-1, keepdims=True)                          # dx x dy
    np.testing.assert_allclose(n[1:-1, 1:-1][valid[1:-1, 1:-1]], want[valid[1:-1, 1:-1]], atol=1e-12)
    assert not n[~valid].any()


class Frame:
    def __init__(self, depth, K, c2w):
        self.depth, self.K, self.cam_to_world = torch.as_tensor(depth), K, c2w


def test_seen_normals_average_the_views_that_see_a_point_and_skip_the_rest():
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    depth = np.ones((48, 64), np.float32)                 # a wall at z = 1 facing the camera
    c2w = np.eye(4)
    turned = np.eye(4)                                    # a camera looking the other way sees nothing of it
    turned[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pts = np.array([[0.0, 0.0, 1.0], [0.05, -0.02, 1.0], [0.0, 0.0, 0.5], [5.0, 0.0, 1.0]])
    n = seen_normals([Frame(depth, K, c2w), Frame(depth, K, turned)], pts, np.full(4, 0.001))
    assert np.allclose(n[:2], [0, 0, -1], atol=1e-6)
    assert not n[2:].any()                                # in front of the wall, off the image
    assert not seen_normals([], pts, np.ones(4)).any()


def look_at(eye, target):
    """cam_to_world [4, 4] (OpenCV axes) of a camera at eye looking at target, z up in the world."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = np.stack([x, np.cross(z, x), z], 1), eye
    return c2w


def cast(boxes, K, c2w, W, H):
    """Depth [H, W] (m) of axis-aligned boxes [(lo, hi)] on the table z = 0, seen by one camera."""
    u, v = np.meshgrid(np.arange(W) + 0.0, np.arange(H) + 0.0)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rays[..., 2] < 0, -o[2] / rays[..., 2], np.inf)                   # the table
        for lo, hi in boxes:
            t0, t1 = (np.asarray(lo) - o) / rays, (np.asarray(hi) - o) / rays
            near, far = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
            t = np.where((near <= far) & (near > 0) & (near < t), near, t)
    return np.where(np.isfinite(t), t, 0.0)   # along the ray of z = 1: the depth


def test_a_pile_seen_by_depth_cameras_splits_into_its_boxes():
    """The chain a point answer runs: keyframe depths (a sensor's noise on them) -> normals seen at
    each Gaussian -> the part at a click, on two boxes that touch, seen from around."""
    A, B = ((0, 0, 0), (0.1, 0.1, 0.1)), ((0.1, 0.02, 0), (0.2, 0.08, 0.06))
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    rng = np.random.default_rng(3)
    frames = []
    for a in np.radians([20, 110, 200, 290]):
        c2w = look_at(np.array([0.1 + 0.5 * np.cos(a), 0.05 + 0.5 * np.sin(a), 0.4]), (0.1, 0.05, 0.03))
        depth = cast([A, B], K, c2w, 160, 120)
        depth = np.where(depth > 0, depth + rng.normal(0, 0.001, depth.shape), 0.0).astype(np.float32)
        frames.append(Frame(depth, K, c2w))
    pts, _, truth = two_boxes()
    nrm = seen_normals(frames, pts, np.full(len(pts), 0.004))
    assert (np.abs(nrm).sum(1) > 0).mean() > 0.8
    for i, click in enumerate([(0.05, 0.05, 0.1), (0.15, 0.05, 0.06)]):
        keep = part_at(pts, nrm, np.array(click))
        assert np.mean(truth[keep] == i) >= 0.95 and keep[truth == i].mean() >= 0.9, (i, keep.sum())


@pytest.mark.parametrize("jitter", [0.0, 8.0])
def test_polishing_moves_strays_at_the_seam_to_the_box_they_continue(jitter):
    pts, nrm, truth = two_boxes(jitter)
    W = seam_graph(pts, nrm)
    seam = np.argsort(np.abs(pts[:, 0] - 0.1))[:12]   # the Gaussians nearest the contact plane x = 0.1
    side = truth.astype(bool)
    side[seam] = ~side[seam]                            # a sweep that cut a little off the seam
    np.testing.assert_array_equal(polished(W, side), truth.astype(bool))
    label = concave_parts(pts, nrm)                     # and the split ends on the seam exactly
    assert max(np.mean(label == truth), np.mean(label != truth)) == 1.0
    # A move that would leave fewer than min_part on a side is not made.
    few = np.zeros(len(pts), bool)
    few[np.flatnonzero(truth == 1)[:3]] = True          # 3 of box B's, bound to B's other Gaussians
    np.testing.assert_array_equal(polished(W, few, min_part=3), few)
    assert not polished(W, few, min_part=0).any()


def test_a_face_only_one_view_sees_is_voted_in_by_that_view_when_asked():
    # points: seen inside by 1 view of 1; inside 1, outside 1; inside 2 of 2; seen by none; outside 1
    inside, outside = np.array([1, 1, 2, 0, 0]), np.array([0, 1, 0, 0, 1])
    v = MaskVotes(inside, outside, inside + outside, np.full(5, 2), np.zeros(5, bool))
    np.testing.assert_array_equal(v.voted(2), [False, False, True, False, False])
    np.testing.assert_array_equal(v.voted(2, by_seen=True), [True, False, True, False, False])
