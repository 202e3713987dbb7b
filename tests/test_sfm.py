"""`rg sfm` (rg_core/io/sfm.py): pycolmap on the CPU recovers the poses of rendered views of a
synthetic table top, the scene folder it writes reads back as a COLMAP scene, and its camera centres
match the renderer's after a similarity alignment; the errors say what is wrong.

20 views at 320x240 (the synthetic ring's views are 18 degrees apart; at 14 or 16 views some seeds
registered only half, the wood and the objects' labels being the only texture), SIFT's contrast
threshold at 0.002 (the default 0.0067 finds ~250 features in such a small render, 0.002 ~600)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from rg_core.cli import main
from rg_core.geometry.points import similarity_transform
from rg_core.io.captures import read_scene, scene_kind
from rg_core.io.images import SceneError, write_rgb
from rg_core.io.scene import read_reasoninggd

pytest.importorskip("pycolmap")
VIEWS, SIZE = 20, (320, 240)
SIFT = ["--sfm.peak_threshold", "0.002", "--sfm.threads", "1"]   # one thread: the same model on every run


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """(folder of the photos, {name: camera-to-world}, fy) of a 20-view synthetic scene."""
    from rg_core.config import SynthConfig
    from rg_core.synth.generator import default_objects_dir, generate_scene

    root = tmp_path_factory.mktemp("sfm")
    generate_scene(root / "scene", SynthConfig(views=VIEWS, width=SIZE[0], height=SIZE[1], objects=5, seed=5, workers=1),
                   default_objects_dir(), progress=False)
    gt = read_reasoninggd(root / "scene")
    photos = root / "photos"
    photos.mkdir()
    for f in gt.frames:
        shutil.copy(f.image_path, photos / f.image_path.name)
    return photos, {f.image_path.name: f.cam_to_world for f in gt.frames}, gt.frames[0].intrinsics.fy


def sfm(capfd, *argv) -> tuple[int, dict]:
    code = main(["sfm", *map(str, argv), *SIFT, "--json", "--quiet"])
    return code, json.loads(capfd.readouterr().out.strip().splitlines()[-1])


def aligned_errors(scene, gt):
    """Camera-centre errors (m) of the scene's frames after the similarity that best maps their
    centres onto the ground truth's, the rotation errors (deg) of the relative poses of consecutive
    registered frames (free of that alignment, whose tilt a near-planar ring of centres pins down
    only to ~0.5 degree), and the similarity's scale."""
    names = [f.image_path.name for f in scene.frames]
    est = np.stack([f.cam_to_world for f in scene.frames])
    ref = np.stack([gt[n] for n in names])
    s, R, t = similarity_transform(est[:, :3, 3], ref[:, :3, 3])
    centres = (s * est[:, :3, 3] @ R.T + t)
    d = np.linalg.norm(centres - ref[:, :3, 3], axis=1)
    rel = lambda P: np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])   # noqa: E731 - R_i^T R_i+1
    diff = np.einsum("nji,njk->nik", rel(est), rel(ref))
    ang = np.degrees(np.arccos(np.clip((np.trace(diff, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return d, ang, s


def test_sfm_recovers_the_cameras_of_rendered_views(views, tmp_path, capfd):
    photos, gt, fy = views
    out = tmp_path / "scene"
    code, summary = sfm(capfd, photos, "--out", out)
    assert code == 0, summary
    assert summary["registered"] == VIEWS and summary["images"] == VIEWS and summary["matcher"] == "exhaustive"
    assert summary["mean_reprojection_error_px"] < 1.0 and summary["points3D"] > 200, summary
    assert scene_kind(out) == "colmap" and (out / "sparse" / "0" / "cameras.bin").is_file()
    assert not (out / ".sfm_models").exists()
    scene = read_scene(out)
    assert scene.kind == "colmap" and len(scene.frames) == VIEWS and scene.world_rule == "points"
    assert all(f.depth_path is None for f in scene.frames) and len(scene.load_points().xyz) == summary["points3D"]
    d, ang, s = aligned_errors(scene, gt)
    # The tolerance: a point triangulated from two views 18 degrees apart (baseline b ~0.19 m) at
    # z ~0.6 m with 0.5 px of SIFT noise at f = 208 px is uncertain by z^2 0.5 / (f b) ~5 mm, and the
    # cameras rest on ~600 such features a view and a focal length found by bundle adjustment.
    # Measured: centres 19 mm at worst, 11 mm median (one thread; 9 and 6 mm on two), 1-3 % of the
    # viewing distance; relative rotations of neighbours 0.5 degree median, 2.1 at worst (the same
    # on two threads: 1.4). Centres within 3 cm (median 1.5 cm) and rotations within 3 degrees leave
    # room for pycolmap's and the CPU's rounding; a wrongly registered view is off by tens of
    # centimetres and degrees.
    assert d.max() < 0.03 and np.median(d) < 0.015 and ang.max() < 3.0, (d.round(4).tolist(), ang.round(3).tolist())
    assert 0.5 < s < 2.0, s   # the auto world scale brought it near metres already (the views are ~0.6 m away)
    import pycolmap

    (cam,) = pycolmap.Reconstruction(str(out / "sparse" / "0")).cameras.values()   # one camera (single_camera)
    f = float(cam.params[0])                   # SIMPLE_RADIAL: f, cx, cy, k (the frames hold its undistorted K)
    assert abs(f - fy) / fy < 0.02, (f, fy)    # the focal length, found by bundle adjustment
    print(f"sfm: centres after alignment max {1000 * d.max():.2f} mm, median {1000 * np.median(d):.2f} mm; "
          f"relative rotation max {ang.max():.3f} deg; focal {f:.1f} px against {fy:.1f}; scale {s:.4f}; "
          f"{summary['seconds']}")


def test_sequential_matching_and_an_incomplete_model(views, tmp_path, capfd):
    photos, gt, _ = views
    # name order only (no loop closure around the ring): 14 of the 20 on one thread here
    code, summary = sfm(capfd, photos, "--out", tmp_path / "seq", "--matcher", "sequential", "--overlap", "6",
                        "--sfm.min_registered", "0.5")
    assert code == 0 and summary["matcher"] == "sequential" and summary["registered"] >= VIEWS // 2, summary
    d, ang, _ = aligned_errors(read_scene(tmp_path / "seq"), gt)
    assert d.max() < 0.03 and ang.max() < 3.0, (d.round(4).tolist(), ang.round(3).tolist())
    more = tmp_path / "more"
    shutil.copytree(photos, more)
    for i in range(6):   # flat photos: no feature, never registered
        write_rgb(more / f"flat_{i}.png", np.full((SIZE[1], SIZE[0], 3), 40 * i, np.uint8))
    code, out = sfm(capfd, more, "--out", tmp_path / "bad")
    assert code == 2
    assert f"pycolmap registered only {VIEWS} of {VIEWS + 6} images (not flat_0.png, flat_1.png" in out["error"], out
    assert "--sfm.min_registered" in out["error"] and not (tmp_path / "bad" / "sparse").exists()
    code, summary = sfm(capfd, more, "--out", tmp_path / "kept", "--sfm.min_registered", "0.7")
    assert code == 0 and summary["registered"] == VIEWS


def test_sfm_errors_name_the_problem(views, tmp_path, capfd):
    from rg_core.io.sfm import run_sfm

    photos, _, _ = views
    with pytest.raises(SceneError, match="image folder not found"):
        run_sfm(tmp_path / "nowhere", tmp_path / "o")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no photos")
    with pytest.raises(SceneError, match=r"holds no photos \(.png, .jpg, .jpeg"):
        run_sfm(tmp_path / "empty", tmp_path / "o")
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(photos / "0003.png", one / "0003.png")
    code, out = sfm(capfd, one, "--out", tmp_path / "o")
    assert code == 2 and "needs at least 2 photos, found 1 (0003.png)" in out["error"]
    two = tmp_path / "two"   # two flat photos: no features, no model
    two.mkdir()
    for i in range(2):
        write_rgb(two / f"{i}.png", np.full((SIZE[1], SIZE[0], 3), 100 + 50 * i, np.uint8))
    code, out = sfm(capfd, two, "--out", tmp_path / "o2")
    assert code == 2 and "pycolmap found no model" in out["error"] and "--sfm.peak_threshold" in out["error"], out
    (tmp_path / "o3" / "sparse").mkdir(parents=True)
    with pytest.raises(SceneError, match="already holds a model"):
        run_sfm(photos, tmp_path / "o3")
