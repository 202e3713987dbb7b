"""Photo worlds defined only up to scale are brought to metres on read (rg_core/io/world_scale.py):
the same synthetic scene written at 1x and at 37x (COLMAP with points, LLFF with bounds, nerfstudio
with cameras only) reads back to the same poses, points and derived scales; a given factor is
applied as it is; scenes in metres are left alone; the map records the factor."""
from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from rg_core.config import MapConfig, PhotoMapConfig
from rg_core.io.captures import read_scene
from rg_core.io.ply import read_ply
from rg_core.io.world_scale import viewing_distance

pytest.importorskip("pycolmap")
from test_photo_scenes import colmap_text, scene_as_llff, scene_as_nerfstudio, w2c_of  # noqa: E402

SCALE = 37.0


@dataclasses.dataclass
class _Scene:   # what the writers read of a scene: its frames
    frames: list


def scaled_frames(scene, s):
    out = []
    for f in scene.frames:
        c2w = np.array(f.cam_to_world, np.float64)
        c2w[:3, 3] *= s
        out.append(dataclasses.replace(f, cam_to_world=c2w))
    return out


def write_colmap(frames, points, root):
    (root / "images").mkdir(parents=True)
    intr = frames[0].intrinsics
    for f in frames:
        shutil.copy(f.image_path, root / "images" / f.image_path.name)
    colmap_text(root / "sparse" / "0",
                [(1, "PINHOLE", intr.width, intr.height, [intr.fx, intr.fy, intr.cx + 0.5, intr.cy + 0.5])],
                [(f.index + 1, *w2c_of(f.cam_to_world), 1, f.image_path.name) for f in frames],
                [(i + 1, p, (128, 128, 128)) for i, p in enumerate(points)])
    return root


@pytest.fixture(scope="module")
def points(synth_scene_dir):
    pts, _ = read_ply(synth_scene_dir / "points3d.ply")
    return pts[np.random.default_rng(0).choice(len(pts), 1500, replace=False)].astype(np.float64)


def assert_same_world(a, b):
    assert [f.image_path.name for f in a.frames] == [f.image_path.name for f in b.frames]
    for fa, fb in zip(a.frames, b.frames):
        np.testing.assert_allclose(fa.cam_to_world, fb.cam_to_world, rtol=1e-9, atol=1e-9)
        assert (fa.bounds is None) == (fb.bounds is None)
        if fa.bounds is not None:
            np.testing.assert_allclose(fa.bounds, fb.bounds, rtol=1e-9)


def test_colmap_at_1x_and_37x_read_to_the_same_world(synth_scene, points, tmp_path):
    one = read_scene(write_colmap(synth_scene.frames, points, tmp_path / "x1"))
    big = read_scene(write_colmap(scaled_frames(synth_scene, SCALE), points * SCALE, tmp_path / "x37"))
    assert one.world_rule == big.world_rule == "points"
    assert big.world_scale == pytest.approx(one.world_scale / SCALE, rel=1e-9)
    assert_same_world(one, big)
    np.testing.assert_allclose(np.sort(one.load_points().xyz, 0), np.sort(big.load_points().xyz, 0), rtol=1e-9, atol=1e-9)
    # the rule's own measure, now in metres: the views' median point depth is world_depth
    for s in (one, big):
        d, rule = viewing_distance(s)
        assert rule == "points" and d == pytest.approx(PhotoMapConfig().world_depth, rel=1e-9)
    # the synthetic world is in metres and seen from about 0.4-0.7 m: auto changes it little
    assert 0.7 < one.world_scale < 1.6, one.world_scale
    # what the photo fit derives from it: the scene extent and the initial Gaussians' sizes
    from rg_core.map.photo_fit import gaussians_from_points, photo_view, scene_extent

    ext = [scene_extent([photo_view(f, 40) for f in s.train]) for s in (one, big)]
    assert ext[0] == pytest.approx(ext[1], rel=1e-9)
    sizes = [gaussians_from_points(s.load_points().xyz, np.full((len(points), 3), 0.5)).scales for s in (one, big)]
    np.testing.assert_allclose(sizes[0].numpy(), sizes[1].numpy(), rtol=1e-5)


def test_llff_bounds_and_nerfstudio_cameras_rules(synth_scene, tmp_path):
    one = read_scene(scene_as_llff(synth_scene, tmp_path / "l1", near_far=(0.2, 5.0)))
    big = read_scene(scene_as_llff(_Scene(scaled_frames(synth_scene, SCALE)), tmp_path / "l37",
                                   near_far=(0.2 * SCALE, 5.0 * SCALE)))
    assert one.world_rule == big.world_rule == "bounds"   # no sparse/0 beside them: the bounds
    assert one.world_scale == pytest.approx(0.6 / np.sqrt(0.2 * 5.0), rel=1e-9)
    assert_same_world(one, big)
    one = read_scene(scene_as_nerfstudio(synth_scene, tmp_path / "n1"))
    big = read_scene(scene_as_nerfstudio(_Scene(scaled_frames(synth_scene, SCALE)), tmp_path / "n37"))
    assert one.world_rule == big.world_rule == "cameras"  # neither points nor bounds: the cameras' spread
    assert_same_world(one, big)


def test_a_given_factor_and_worlds_in_metres(synth_scene, synth_scene_dir, points, tmp_path):
    root = write_colmap(synth_scene.frames, points, tmp_path / "c")
    s = read_scene(root, photo=PhotoMapConfig(world_scale=2.5))
    assert (s.world_scale, s.world_rule) == (2.5, "given")
    for a, b in zip(s.frames, synth_scene.frames):
        np.testing.assert_allclose(a.cam_to_world[:3, 3], 2.5 * b.cam_to_world[:3, 3], rtol=1e-9)
        np.testing.assert_allclose(a.cam_to_world[:3, :3], b.cam_to_world[:3, :3], atol=1e-9)
    np.testing.assert_allclose(np.sort(s.load_points().xyz, 0), np.sort(2.5 * points, 0), rtol=1e-9)
    rgbd = read_scene(synth_scene_dir, photo=PhotoMapConfig(world_scale=2.5))   # depth fixes the unit
    assert (rgbd.world_scale, rgbd.world_rule) == (1.0, "metric")
    for a, b in zip(rgbd.frames, synth_scene.frames):
        np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)


def test_the_map_records_the_factor(synth_scene, points, tmp_path):
    from rg_core.map.run import build_map
    from rg_core.map.store import load_map, save_map

    big = read_scene(write_colmap(scaled_frames(synth_scene, SCALE), points * SCALE, tmp_path / "x37"))
    cfg = PhotoMapConfig(iters=4, check_every=2, densify_from=100, converge_db=0.0)
    mapper, built = build_map(big, MapConfig(width=40, final_iters=0), cfg, progress=False)
    assert built["world_scale"] == big.world_scale and built["world_rule"] == "points" and built["kind"] == "photo"
    back = load_map(save_map(mapper, tmp_path / "m.rgmap"))
    assert back.built["world_scale"] == pytest.approx(big.world_scale, rel=1e-12)
    assert back.built["photo"]["heldout_psnr"] == built["photo"]["heldout_psnr"]
    # the fit works in metres: its Gaussians lie within a few metres of the cameras, not 37x further
    c = np.stack([kf.cam_to_world[:3, 3] for kf in mapper.keyframes])
    assert np.median(np.linalg.norm(mapper.gaussians.means.numpy() - c.mean(0), axis=1)) < 2.0
