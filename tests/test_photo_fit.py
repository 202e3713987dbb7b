"""Maps from posed photos without depth (rg_core/map/photo_fit.py, issue 63): the fit learns the
views, density control clones, splits and prunes within max_gaussians, the stop test ends it, and
the degenerate inputs are refused or survived."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from rg_core.config import MapConfig, PhotoMapConfig
from rg_core.eval.mapping import psnr
from rg_core.io.captures import read_scene
from rg_core.io.ply import read_ply
from rg_core.map.frames import prepare_frame
from rg_core.map.gaussians import PARAMS
from rg_core.map.photo_fit import (PhotoFitter, PhotoView, gaussians_from_points, initial_points, rendered_depth,
                                   step_ceiling)
from rg_core.map.photo_losses import depth_smoothness, ssim

WIDTH = 80


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("photo") / "scene"
    subprocess.run([sys.executable, "-m", "rg_core.cli", "synth", str(out), "--views", "12", "--size", "160x120",
                    "--seed", "713", "--objects", "3", "--quiet"], check=True, capture_output=True)
    sc = read_scene(out, test_every=6)

    def views(frames):
        vs = []
        for f in frames:
            fr = prepare_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, f.stamp, WIDTH)
            vs.append((PhotoView(torch.from_numpy(fr.rgb).float(), fr.K, fr.cam_to_world, f.index), fr.depth))
        return vs

    pts, cols = read_ply(out / "points3d.ply")
    sel = np.random.default_rng(0).choice(len(pts), min(1500, len(pts)), replace=False)
    cols = cols[sel].astype(np.float64)
    cols = cols / 255.0 if cols.max() > 1 else cols
    return dict(train=views(sc.train), test=views(sc.test), points=pts[sel], colors=cols, frames=sc.train)


CFG = PhotoMapConfig(iters=240, check_every=40, densify_from=40, densify_every=40, densify_until=0.6,
                     reset_opacity_every=0, converge_db=0.0)


def _test_psnr(fitter, fit, views):
    with torch.no_grad():
        return float(np.mean([psnr(fitter._render(v, fit.gaussians.tensors())[1].numpy(), v.rgb.numpy())
                              for v, _ in views]))


def test_fit_learns_the_views_and_controls_density(scene):
    train = [v for v, _ in scene["train"]]
    f = PhotoFitter(train, CFG, MapConfig(width=WIDTH), scene["points"], scene["colors"])
    before = _test_psnr(f, type("F", (), {"gaussians": f.g})(), scene["test"])
    fit = f.fit(progress=False)
    after = _test_psnr(f, fit, scene["test"])
    first, last = fit.history[0][2], fit.history[-1][2]
    assert last > first + 2.0, fit.history                       # held-out pixels: it learns, not memorises
    assert after > before + 3.0 and after > 18.0, (before, after)  # views it never saw
    assert fit.totals["split"] + fit.totals["cloned"] > 0 and fit.stopped == "budget" and fit.steps == CFG.iters
    n = len(fit.gaussians)
    for k in PARAMS:                                              # moments follow every clone, split and prune
        assert f.optim.m[k].shape[0] == n and f.optim.v[k].shape[0] == n
    assert all(torch.isfinite(t).all() for t in fit.gaussians.tensors().values())


def test_max_gaussians_bounds_density_control(scene):
    train = [v for v, _ in scene["train"]]
    cap = len(scene["points"]) + 100
    f = PhotoFitter(train, dataclasses.replace(CFG, iters=120), MapConfig(width=WIDTH, max_gaussians=cap),
                    scene["points"], scene["colors"])
    fit = f.fit(progress=False)
    assert fit.totals["split"] + fit.totals["cloned"] > 0
    assert max(h[3] for h in fit.history) <= cap and len(fit.gaussians) <= cap


def test_stop_test_ends_the_fit_before_the_ceiling(scene):
    train = [v for v, _ in scene["train"]]
    cfg = dataclasses.replace(CFG, iters=2000, steps_per_view=0, densify_until=0.05, converge_db=0.5, converge_window=80)
    fit = PhotoFitter(train, cfg, MapConfig(width=WIDTH), scene["points"], scene["colors"]).fit(progress=False)
    assert fit.ceiling == 2000 and fit.stopped == "converged" and fit.steps < fit.ceiling, (fit.stopped, fit.steps)


def test_step_ceiling_grows_with_the_views_between_its_bounds(scene):
    """Defaults: 1000 steps up to 28 views, 35 a view above, 7000 at most; steps_per_view 0: iters."""
    c = PhotoMapConfig()
    assert [step_ceiling(c, n) for n in (1, 17, 28, 29, 87, 199, 200, 5000)] == [1000, 1000, 1000, 1015, 3045, 6965,
                                                                                   7000, 7000]
    assert step_ceiling(dataclasses.replace(c, steps_per_view=0), 100) == 7000
    assert step_ceiling(dataclasses.replace(c, iters=240), 100) == 240          # iters stays the hard ceiling
    train = [v for v, _ in scene["train"]]
    assert PhotoFitter(train, c, MapConfig(width=WIDTH), scene["points"], scene["colors"]).cfg.iters == 1000


def test_random_initialisation_without_points_learns(scene):
    train = [v for v, _ in scene["train"]]
    cfg = dataclasses.replace(CFG, iters=160, init_random=1500)
    f = PhotoFitter(train, cfg, MapConfig(width=WIDTH))
    fit = f.fit(progress=False)
    assert fit.history[-1][2] > fit.history[0][2] + 1.0, fit.history


def test_random_initial_points_fill_the_frusta_seeded(scene):
    """View uniform, pixel uniform, depth uniform in inverse depth; the same seed the same points.
    Two views looking opposite ways (their frusta never meet) of different sizes and focal lengths."""
    from rg_core.geometry.conventions import look_at, project

    K1 = np.array([[40.0, 0, 39.5], [0, 40.0, 29.5], [0, 0, 1]])
    K2 = np.array([[25.0, 0, 19.5], [0, 25.0, 14.5], [0, 0, 1]])
    views = [PhotoView(torch.zeros(60, 80, 3), K1, look_at(np.zeros(3), np.array([0.0, 1, 0]))),
             PhotoView(torch.zeros(30, 40, 3), K2, look_at(np.zeros(3), np.array([0.0, -1, 0])))]
    near, far, n = 0.1, 5.0, 6000
    pts, cols = initial_points(views, n, near, far, np.random.default_rng(3))
    again, _ = initial_points(views, n, near, far, np.random.default_rng(3))
    other, _ = initial_points(views, n, near, far, np.random.default_rng(4))
    np.testing.assert_array_equal(pts, again)
    assert not np.allclose(pts, other) and pts.shape == (n, 3) and (cols == 0.5).all()
    first = pts[:, 1] > 0                                          # in front of view 0, behind view 1
    assert abs(first.mean() - 0.5) < 0.03, first.mean()
    for v, sel in ((views[0], first), (views[1], ~first)):
        h, w = v.rgb.shape[:2]
        uv, z = project(pts[sel], v.K, v.cam_to_world)
        assert (z >= near * (1 - 1e-9)).all() and (z <= far * (1 + 1e-9)).all()
        assert (uv >= -1e-6).all() and (uv[:, 0] <= w + 1e-6).all() and (uv[:, 1] <= h + 1e-6).all()
        for x, lo, hi in ((uv[:, 0], 0, w), (uv[:, 1], 0, h), (1 / z, 1 / far, 1 / near)):   # uniform: KS distance
            x = np.sort((x - lo) / (hi - lo))
            assert np.abs(x - (np.arange(len(x)) + 0.5) / len(x)).max() < 0.04


def test_rendered_depth_is_the_surface_where_opaque(scene):
    train = [v for v, _ in scene["train"]]
    f = PhotoFitter(train, CFG, MapConfig(width=WIDTH), scene["points"], scene["colors"])
    fit = f.fit(progress=False)
    v, sensor = scene["train"][0]
    d = rendered_depth(fit.gaussians, v, MapConfig(width=WIDTH)).numpy()
    assert np.isfinite(d).all() and (d >= 0).all()
    both = (d > 0) & (sensor > 0)
    assert both.mean() > 0.5                                      # most of the view is covered
    assert np.median(np.abs(d[both] - sensor[both]) / sensor[both]) < 0.1


def test_degenerate_points_and_views():
    with pytest.raises(ValueError, match="at least 4 finite initial points"):
        gaussians_from_points(np.array([[0, 0, 1.0], [np.nan, 0, 1], [0, np.inf, 1]]), np.full((3, 3), 0.5))
    dup = np.repeat([[0.0, 0.0, 1.0]], 8, axis=0)                  # duplicates: no zero scale, no NaN
    g = gaussians_from_points(dup, np.full((8, 3), 0.5))
    assert torch.isfinite(g.log_scales).all() and (g.scales > 0).all()
    with pytest.raises(ValueError, match="no views"):
        PhotoFitter([], CFG)


def test_ssim_of_equal_images_is_one_and_drops_with_noise():
    a = torch.rand(40, 50, 3, generator=torch.Generator().manual_seed(0))
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-5)
    b = (a + 0.2 * torch.randn(40, 50, 3, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    assert float(ssim(a, b)) < 0.9
    assert math.isfinite(float(ssim(torch.zeros(8, 8, 3), torch.zeros(8, 8, 3))))   # smaller than the window


def test_depth_smoothness_follows_the_photo_and_stays_finite():
    flat, ones = torch.full((20, 30), 0.8), torch.ones(20, 30)
    grey = torch.full((20, 30, 3), 0.5)
    assert float(depth_smoothness(flat, ones, grey)) == 0.0
    step = flat.clone()
    step[:, 15:] = 1.2                                               # a depth jump along column 15
    edge = grey.clone()
    edge[:, 15:] = 0.9                                               # ... where the photo has an edge
    at_edge, in_plain = float(depth_smoothness(step, ones, edge)), float(depth_smoothness(step, ones, grey))
    assert 0 < at_edge < 0.05 * in_plain                             # a jump at a colour edge costs ~nothing
    assert float(depth_smoothness(step * 1000, ones, grey)) == pytest.approx(in_plain, rel=1e-4)   # relative to depth
    d = step.clone().requires_grad_(True)
    depth_smoothness(d, ones, grey).backward()
    assert torch.isfinite(d.grad).all() and float(d.grad.abs().sum()) > 0
    for alpha in (torch.zeros(20, 30), torch.full((20, 30), 0.3)):   # nothing opaque: no term, no NaN
        assert float(depth_smoothness(step, alpha, grey)) == 0.0
    tiny = torch.full((20, 30), 1e-9)
    assert math.isfinite(float(depth_smoothness(tiny, ones, grey)))


def test_depth_smoothness_term_trains_and_stays_finite(scene):
    cfg = dataclasses.replace(CFG, iters=60, depth_smoothness=0.5, holdout_views=0.0)
    fitter = PhotoFitter([v for v, _ in scene["train"]], cfg, points=scene["points"], colors=scene["colors"])
    fit = fitter.fit(progress=False)
    assert fit.steps == 60 and all(bool(torch.isfinite(t).all()) for t in fit.gaussians.tensors().values())


# ------------------------------------------------------------------------------ the scene without depth, end to end

@pytest.fixture(scope="module")
def photo_scene(tmp_path_factory):
    """A synthetic scene with its depth images and depth_file_path entries removed (the
    ReasoningGD layout of photos alone) and a 1,500-point sparse cloud."""
    from conftest import photos_only

    out = tmp_path_factory.mktemp("photo_only") / "scene"
    subprocess.run([sys.executable, "-m", "rg_core.cli", "synth", str(out), "--views", "12", "--size", "160x120",
                    "--seed", "714", "--objects", "3", "--quiet"], check=True, capture_output=True)
    return photos_only(out)


def test_a_scene_without_depth_maps_by_the_photo_fit_and_grounds(photo_scene, tmp_path):
    from rg_core.config import FieldConfig, RGConfig
    from rg_core.grounding.build import build_grounder
    from rg_core.map.run import build_map
    from rg_core.map.store import load_map, save_map

    sc = read_scene(photo_scene, test_every=6)
    assert not sc.has_depth()
    mc = MapConfig(width=WIDTH, final_iters=0)
    mapper, built = build_map(sc, mc, dataclasses.replace(CFG, iters=160), progress=False)
    assert built["kind"] == "photo" and built["photo"]["steps"] == 160
    assert len(mapper.keyframes) == len(sc.train)
    assert all(float((kf.depth > 0).float().mean()) > 0.5 for kf in mapper.keyframes)   # rendered depth
    back = load_map(save_map(mapper, tmp_path / "photo.rgmap"))
    assert len(back.gaussians) == len(mapper.gaussians) and len(back.keyframes) == len(mapper.keyframes)
    cfg = RGConfig(map=mc, photo=dataclasses.replace(CFG, iters=160), field=FieldConfig(steps=150))
    g, report = build_grounder(sc, cfg, supervision="oracle", mapper=mapper)
    q = sc.queries[0]
    obj = next(o for o in sc.objects if o.id == q.object_id)
    res = g.ground(q.explicit)
    assert res.success, res.message
    centre = (np.asarray(res.objects[0].aabb_min) + np.asarray(res.objects[0].aabb_max)) / 2
    lo, hi = np.asarray(obj.aabb_min) - 0.05, np.asarray(obj.aabb_max) + 0.05
    assert ((centre >= lo) & (centre <= hi)).all(), (q.explicit, centre, obj.aabb_min, obj.aabb_max)


def test_a_scene_with_depth_on_some_frames_only_is_refused(photo_scene, tmp_path):
    from rg_core.io.images import SceneError
    from rg_core.map.run import build_map

    sc = read_scene(photo_scene, test_every=6)
    sc.train[0].depth_path = tmp_path / "0000.png"   # one frame claims a depth image
    with pytest.raises(SceneError, match="no depth images"):
        build_map(sc, MapConfig(width=WIDTH), CFG, progress=False)


# ------------------------------------------------------------------------------ held-out views, extent, initialisation

def test_heldout_views_lie_between_trained_ones():
    from rg_core.map.photo_fit import heldout_views

    assert heldout_views(17, 0.1) == [4, 12] and heldout_views(20, 0.1) == [5, 15]
    assert heldout_views(10, 0.1) == [5] and heldout_views(3, 0.1) == [1]   # at least one of 3 or more
    assert heldout_views(2, 0.1) == [] and heldout_views(17, 0.0) == []
    assert len(heldout_views(100, 0.1)) == 10


def test_heldout_views_are_trained_on_only_after_the_stop_is_decided(scene):
    train = [v for v, _ in scene["train"]]
    f = PhotoFitter(train, dataclasses.replace(CFG, iters=200), MapConfig(width=WIDTH), scene["points"], scene["colors"])
    assert f.held and not f.joined
    seen, render = [], f._render

    def spy(v, params):
        if torch.is_grad_enabled():                  # a training step (the stop test renders without grad)
            seen.append((len(seen) + 1, v.index))
        return render(v, params)

    f._render = spy
    fit = f.fit(progress=False)
    held = {train[i].index for i in fit.heldout}
    assert fit.decided == 170 and fit.steps == 200 and fit.history[-1][0] == fit.decided   # (1 - 0.15) x 200
    assert not any(i in held for s, i in seen if s <= fit.decided)
    assert any(i in held for s, i in seen if s > fit.decided)
    assert len(seen) == fit.steps


def test_extent_is_at_least_the_viewing_distance():
    from rg_core.geometry.conventions import look_at
    from rg_core.map.photo_fit import scene_extent, viewing_depth

    K = np.array([[40.0, 0, 39.5], [0, 40.0, 29.5], [0, 0, 1]])
    views = [PhotoView(torch.zeros(60, 80, 3), K, look_at(np.array([0.003 * i, 0, 0]), np.array([0.0, 0, 1])))
             for i in range(3)]                       # near-static cameras, 6 mm apart
    pts = np.random.default_rng(0).uniform([-0.3, -0.2, 1.0], [0.3, 0.2, 1.4], (400, 3))
    d = viewing_depth(views, pts)
    assert 1.1 < d < 1.3
    assert scene_extent(views) == pytest.approx(0.1) and scene_extent(views, d) == pytest.approx(d)
    assert viewing_depth(views, -pts) is None          # all behind the cameras


def test_random_start_lies_around_the_viewing_distance(scene, monkeypatch):
    """Without points the depths are drawn within a factor 2 of the viewing distance (the hint, else
    photo.world_depth), not from map.near to 10 x the extent."""
    import rg_core.map.photo_fit as pf

    got, draw = [], pf.initial_points
    monkeypatch.setattr(pf, "initial_points", lambda views, n, near, far, rng: got.append((near, far)) or
                        draw(views, n, near, far, rng))
    train = [v for v, _ in scene["train"]]
    f = PhotoFitter(train, dataclasses.replace(CFG, init_random=500), MapConfig(width=WIDTH), depth_hint=0.8)
    assert got[-1] == pytest.approx((0.4, 1.6)) and f.depth == 0.8 and f.extent >= 0.8
    f = PhotoFitter(train, dataclasses.replace(CFG, init_random=500, world_depth=0.5), MapConfig(width=WIDTH))
    assert got[-1] == pytest.approx((0.25, 1.0)) and len(f.g) == 500


def test_triangulation_at_known_poses_finds_the_surface(tmp_path):
    """A scene with poses but no points: pycolmap's matches triangulated at the frames' poses lie on
    the scene's surface (the synthetic sensor depth, which the triangulation never reads)."""
    from rg_core.geometry.conventions import project
    from rg_core.io.sfm import triangulate_posed

    out = tmp_path / "scene"
    subprocess.run([sys.executable, "-m", "rg_core.cli", "synth", str(out), "--views", "12", "--size", "320x240",
                    "--seed", "715", "--objects", "7", "--quiet"], check=True, capture_output=True)
    frames = read_scene(out).train
    pts = triangulate_posed(frames)
    assert pts is not None and len(pts.xyz) >= 50 and pts.rgb.dtype == np.uint8, pts
    for f in frames[:3]:
        depth = f.load_depth()
        h, w = depth.shape
        uv, z = project(pts.xyz, f.intrinsics.K, f.cam_to_world)
        px = np.round(uv).astype(int)
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        sensor = depth[px[ok, 1], px[ok, 0]]
        good = sensor > 0
        assert good.sum() >= 20
        assert np.median(np.abs(z[ok][good] - sensor[good]) / sensor[good]) < 0.05
