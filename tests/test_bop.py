"""BOP-format scenes (issue 19) on real photos: YCB-Video 0002 (20 frames, six objects), the pose
convention, poses from a static object, the amodal-coverage figure, bad inputs, rg eval --queries
and a small end-to-end rg map."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from rg_core.io.bop import BopOptions, read_bop
from rg_core.io.queries import read_queries
from rg_core.io.captures import read_scene
from rg_core.io.images import SceneError

YCBV = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rgbd" / "ycbv_0002_bop"
NAMES = {5: "mustard bottle", 7: "pudding box", 9: "potted meat can", 10: "banana", 16: "wood block",
         18: "large marker"}


@pytest.fixture(scope="module")
def ycbv() -> Path:
    if not YCBV.is_dir():
        pytest.skip(f"{YCBV} is missing (../shared/data beside the checkout)")
    return YCBV


@pytest.fixture(scope="module")
def scene(ycbv):
    return read_scene(ycbv)


def copy_bop(src: Path, dst: Path, ims: list[int], drop_cam_pose: bool = False) -> Path:
    """A small BOP scene with images `ims` of `src` (json filtered, files copied, models linked)."""
    dst.mkdir(parents=True)
    for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        data = json.loads((src / name).read_text())
        data = {k: v for k, v in data.items() if int(k) in ims}
        if drop_cam_pose and name == "scene_camera.json":
            for v in data.values():
                v.pop("cam_R_w2c"), v.pop("cam_t_w2c")
        (dst / name).write_text(json.dumps(data))
    shutil.copy(src / "obj_names.json", dst)
    (dst / "models").symlink_to(src / "models")
    for d in ("rgb", "depth", "mask", "mask_visib"):
        (dst / d).mkdir()
        for i in ims:
            for p in (src / d).glob(f"{i:06d}*.png"):
                shutil.copy(p, dst / d / p.name)
    return dst


def edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def test_reader_on_ycbv_0002(scene):
    assert scene.kind == "bop" and len(scene.frames) == 20
    assert [f.index for f in scene.test] == [1, 9, 17] and len(scene.train) == 17  # every 8th image
    f = scene.frames[0]
    assert (f.intrinsics.width, f.intrinsics.height) == (640, 480)
    np.testing.assert_allclose(f.intrinsics.K, [[1066.778, 0, 312.9869], [0, 1067.487, 241.3109], [0, 0, 1]])
    assert f.depth_scale == pytest.approx(10000.0)  # BOP depth_scale 0.1 mm per unit -> 10000 units per metre
    d = f.load_depth()
    assert 1.0 < np.median(d[d > 0]) < 1.2  # the table about 1.1 m away
    assert {o.id: o.name for o in scene.objects} == NAMES
    for o in scene.objects:  # YCB objects: 2-25 cm per side
        ext = np.array(o.aabb_max) - np.array(o.aabb_min)
        assert np.all(ext > 0.015) and np.all(ext < 0.25), (o.name, ext)
    assert {q.object_id for q in scene.queries} == set(NAMES)
    assert all(q.explicit == NAMES[q.object_id] and len(q.implicit) >= 5 for q in scene.queries)  # description set


def test_masks_reach_evaluation_like_synthetic_ones(scene):
    f = scene.test[0]
    ids = f.load_visible_mask()
    assert ids.dtype == np.uint8 and ids.shape == (480, 640)
    assert set(np.unique(ids)) == {0} | set(NAMES)
    for oid in NAMES:
        amodal = f.load_complete_mask(oid)
        vis = ids == oid
        assert amodal.sum() >= 0.98 * vis.sum() and vis.sum() > 1000  # a fully visible object: about equal
        assert (vis & amodal).sum() / vis.sum() > 0.99  # SOURCE.md: 99.8-99.9 % of visible lies in amodal


def backproject(f, mask):  # world points [N, 3] of a mask's valid depth pixels
    d = f.load_depth()
    ys, xs = np.nonzero(mask & (d > 0))
    z = d[ys, xs]
    K = f.intrinsics.K
    cam = np.stack([(xs - K[0, 2]) * z / K[0, 0], (ys - K[1, 2]) * z / K[1, 1], z], 1)
    return cam @ f.cam_to_world[:3, :3].T + f.cam_to_world[:3, 3]


def test_pose_convention_depth_lands_in_object_boxes(scene):
    """Camera-to-world in OpenCV axes, metres: each object's visible pixels back-projected with the
    sensor depth fall inside that object's world box (built from the model and the BOP pose)."""
    for f in (scene.frames[0], scene.frames[-1]):
        ids = f.load_visible_mask()
        for o in scene.objects:
            pts = backproject(f, ids == o.id)
            inside = np.all((pts > np.array(o.aabb_min) - 0.01) & (pts < np.array(o.aabb_max) + 0.01), 1)
            assert inside.mean() > 0.9, (f.index, o.name, inside.mean())


def test_two_views_depth_agree(scene):
    """View 1's depth, moved into view 20 by the poses, matches view 20's depth (SOURCE.md: 2.2 mm)."""
    a, b = scene.frames[0], scene.frames[-1]
    pts = backproject(a, np.ones((480, 640), bool))[::7]
    w2c = np.linalg.inv(b.cam_to_world)
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    K = b.intrinsics.K
    x = np.round(cam[:, 0] / cam[:, 2] * K[0, 0] + K[0, 2]).astype(int)
    y = np.round(cam[:, 1] / cam[:, 2] * K[1, 1] + K[1, 2]).astype(int)
    ok = (x >= 0) & (x < 640) & (y >= 0) & (y < 480)
    db = b.load_depth()[y[ok], x[ok]]
    err = np.abs(db - cam[ok, 2])[db > 0]
    assert np.median(err) < 0.006, np.median(err)
    # a wrong convention (the inverse pose) does much worse
    bad = pts @ b.cam_to_world[:3, :3].T + b.cam_to_world[:3, 3]
    assert np.median(np.abs(bad[:, 2] - np.median(db))) > 0.05


def test_split_and_single_image_are_configurable(ycbv):
    s = read_bop(ycbv, BopOptions(test_every=4))
    assert [f.index for f in s.test] == [1, 5, 9, 13, 17] and len(s.train) == 15
    s = read_bop(ycbv, BopOptions(test_every=0))
    assert not s.test and len(s.train) == 20
    s = read_bop(ycbv, BopOptions(single_image=7))
    assert [f.index for f in s.train] == [7] == [f.index for f in s.test]
    with pytest.raises(SceneError, match="no image 99"):
        read_bop(ycbv, BopOptions(single_image=99))


def test_poses_from_a_static_object(ycbv, tmp_path):
    """Without cam_R_w2c the world is the most visible object's frame; the recovered camera motion
    between images matches the real poses' within a few mm."""
    ims = [1, 6, 12, 20]
    real = {f.index: f.cam_to_world for f in read_bop(ycbv).frames if f.index in ims}
    s = read_bop(copy_bop(ycbv, tmp_path / "s", ims, drop_cam_pose=True))
    assert s.bop["anchor_object"] in NAMES and "static object" in s.bop["camera_poses"]
    got = {f.index: f.cam_to_world for f in s.frames}
    for i in ims[1:]:
        rel_real = np.linalg.inv(real[1]) @ real[i]
        rel_got = np.linalg.inv(got[1]) @ got[i]
        assert np.linalg.norm(rel_real[:3, 3] - rel_got[:3, 3]) < 0.003
        cos = (np.trace(rel_real[:3, :3].T @ rel_got[:3, :3]) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 0.3
    # the world is the anchor's model frame: the anchor's world box is its model's box
    anchor = next(o for o in s.objects if o.id == s.bop["anchor_object"])
    assert np.all(np.abs(np.array(anchor.aabb_min)) < 0.15)
    s1 = read_bop(tmp_path / "s", BopOptions(anchor_object=10))
    assert s1.bop["anchor_object"] == 10


def test_moving_object_is_refused(ycbv, tmp_path):
    root = copy_bop(ycbv, tmp_path / "s", [1, 6, 12], drop_cam_pose=True)

    def move_banana(gt):
        e = next(e for e in gt["12"] if e["obj_id"] == 10)
        e["cam_t_m2c"][0] += 40.0  # 4 cm
    edit_json(root / "scene_gt.json", move_banana)
    with pytest.raises(SceneError, match=r"scene_gt\.json: objects move relative.*'banana'.*obj_id 10"):
        read_bop(root)
    s = read_bop(root, BopOptions(single_image=12))  # one image alone needs no static scene
    assert len(s.frames) == 1 and len(s.objects) == 6
    s = read_bop(root, BopOptions(static_tol_m=0.05))  # a looser tolerance accepts it
    assert len(s.frames) == 3


def test_bad_inputs_name_the_file(ycbv, tmp_path):
    root = copy_bop(ycbv, tmp_path / "a", [1, 2, 3])
    (root / "depth" / "000002.png").unlink()
    with pytest.raises(SceneError, match=r"depth/000002\.png: file not found"):
        read_bop(root)

    root = copy_bop(ycbv, tmp_path / "b", [1, 2, 3])
    cv2.imwrite(str(root / "mask_visib" / "000003_000002.png"), np.zeros((240, 320), np.uint8))
    with pytest.raises(SceneError, match=r"mask_visib/000003_000002\.png: image is 320x240, expected 640x480"):
        read_bop(root)

    root = copy_bop(ycbv, tmp_path / "c", [1, 2, 3])
    edit_json(root / "scene_gt.json", lambda gt: gt.__setitem__("4", gt["3"]))
    with pytest.raises(SceneError, match=r"scene_gt\.json: image 4 has annotations but no entry in scene_camera"):
        read_bop(root)
    edit_json(root / "scene_camera.json", lambda c: c.__setitem__("4", c["3"]))
    with pytest.raises(SceneError, match=r"scene_gt\.json: image 4 has annotations but .*rgb/000004\.png does not exist"):
        read_bop(root)

    root = copy_bop(ycbv, tmp_path / "d", [1, 2, 3])
    for wrong, right in ((100.0, "0.1"), (0.0001, "0.1")):  # metres / micro-scale confusions
        edit_json(root / "scene_camera.json", lambda c: [v.__setitem__("depth_scale", wrong) for v in c.values()])
        with pytest.raises(SceneError, match=rf"scene_camera\.json: image 1: depth_scale .* did you mean depth_scale {right}\?"):
            read_bop(root)


def test_queries_file(scene, tmp_path):
    p = tmp_path / "q.json"
    p.write_text(json.dumps([{"object_id": 10, "explicit": "banana", "implicit": ["a yellow curved fruit"]},
                             {"object": "mustard bottle", "implicit": "something for a hot dog"}]))
    qs = read_queries(p, scene.objects)
    assert [(q.object_id, q.explicit, q.implicit) for q in qs] == [
        (10, "banana", ["a yellow curved fruit"]), (5, "mustard bottle", ["something for a hot dog"])]
    p.write_text(json.dumps([{"object_id": 3, "explicit": "cup", "implicit": []}]))
    with pytest.raises(SceneError, match=r"q\.json: query 0: object_id 3 is not an object of the scene"):
        read_queries(p, scene.objects)


def run_rg(*args):
    return subprocess.run([sys.executable, "-m", "rg_core.cli", *args], capture_output=True, text=True, timeout=300)


def test_rg_eval_queries_errors_name_the_file(ycbv, tmp_path):
    p = tmp_path / "queries.json"
    p.write_text(json.dumps({"object_id": 5}))
    r = run_rg("eval", str(ycbv), "--queries", str(p), "--json", "--quiet")
    assert r.returncode == 2
    assert "queries.json: expected a JSON list of queries" in json.loads(r.stdout)["error"]


def test_amodal_coverage_on_one_viewpoint(scene):
    """With a nearly static camera, the never-seen share of a test view's amodal mask is about
    what that view itself hides (1 - visible/amodal): mustard bottle and wood block are half hidden."""
    from rg_core.eval.amodal_coverage import amodal_coverage

    cov = amodal_coverage(scene, n_points=60_000)
    assert set(cov) == set(NAMES.values())
    for name, c in cov.items():
        assert c["unseen_fraction"] == pytest.approx(c["hidden_in_test_view"], abs=0.06), (name, c)
        assert 0.15 < c["surface_seen"] < 0.6  # one side of each object
    assert cov["wood block"]["unseen_fraction"] > 0.25 and cov["mustard bottle"]["unseen_fraction"] > 0.15
    assert cov["banana"]["unseen_fraction"] < 0.03


def fast_config(tmp_path) -> str:
    cfg = tmp_path / "fast.yaml"
    cfg.write_text("map:\n  final_iters: 30\n")
    return str(cfg)


def test_rg_map_on_bop_folder(ycbv, tmp_path):
    r = run_rg("--config", fast_config(tmp_path), "map", str(ycbv), "--out", str(tmp_path / "m.rgmap"), "--width", "160",
               "--iters-per-keyframe", "2", "--max-gaussians", "5000", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["train_frames"] == 17 and out["test_frames"] == 3 and out["test"]["views"] == 3
    assert 0 < out["gaussians"] <= 5000 and out["test"]["psnr"] > 12
    assert out["test"]["depth_abs_error_median_m"] < 0.05
    assert (tmp_path / "m.rgmap").is_file()


def test_rg_eval_with_own_queries_on_bop(ycbv, tmp_path):
    """`rg eval --queries` runs exactly the file's queries on the BOP test views and reports the
    per-object figures and the amodal unseen fraction (a tiny map: the figures are not checked)."""
    r = run_rg("--config", fast_config(tmp_path), "map", str(ycbv), "--out", str(tmp_path / "m.rgmap"), "--width", "80", "--iters-per-keyframe", "1",
               "--max-gaussians", "2000", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    q = tmp_path / "q.json"
    q.write_text(json.dumps([{"object_id": 10, "explicit": "banana", "implicit": ["a curved yellow fruit"]}]))
    r = run_rg("eval", str(ycbv), "--map", str(tmp_path / "m.rgmap"), "--queries", str(q), "--supervision", "oracle",
               "--field-seconds", "0", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    ev = json.loads(r.stdout)["eval"]
    assert ev["explicit"]["queries"] == 1 and ev["implicit"]["queries"] == 1
    assert ev["explicit"]["pairs"] == 3  # the banana is visible in the 3 test views
    assert set(ev["per_object"]) == {"banana"} and set(ev["box_iou"]["per_object"]) == {"banana"}
    assert ev["amodal_unseen"]["banana"]["unseen_fraction"] < 0.05
    assert ev["amodal_unseen"]["wood block"]["unseen_fraction"] > 0.25


def test_near_static_camera_config_loads():
    from rg_core.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[1] / "config" / "near_static_camera.yaml")
    assert cfg.map.kf_new_fraction == 0.0 and cfg.map.kf_photo_error == 0.0


def test_rg_report_accepts_a_bop_folder(ycbv, tmp_path):
    r = run_rg("report", str(ycbv), "--out", str(tmp_path / "rep"), "--tiny", "--sections", "mapping", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["failed_sections"] == [] and out["headline"]["mapping"][0]["PSNR dB"] > 15
    assert (tmp_path / "rep" / "report.md").is_file()


def test_pca_fits_a_one_keyframe_supervision():
    """One keyframe of ycbv_0002 under oracle supervision has 7 masks, below the incremental PCA's
    8: a finished supervision set fits on what it has (else the field never trains)."""
    import torch

    from rg_core.perception.pca import IncrementalPCA

    p = IncrementalPCA(k=64)
    x = torch.randn(7, 384)
    assert not p.add(x) and p.pca is None
    assert p.fit_now() and p.pca is not None and not p.fit_now()
    back = p.pca.inverse(p.pca.transform(x))
    assert torch.allclose(back, x, atol=1e-4)  # 7 rows span at most 7 dimensions: kept exactly
    assert not IncrementalPCA().fit_now()  # nothing to fit


def test_names_without_obj_names_json(ycbv, tmp_path):
    """No obj_names.json and no names in models_info.json: BOP's YCB-V list by id, or 'object N'."""
    root = copy_bop(ycbv, tmp_path / "s", [1, 2])
    (root / "obj_names.json").unlink()
    (root / "models").unlink()
    (root / "models").mkdir()
    for p in (ycbv / "models").glob("obj_*.ply"):
        (root / "models" / p.name).symlink_to(p)
    assert {o.id: o.name for o in read_bop(root).objects} == NAMES
    assert {o.name for o in read_bop(root, BopOptions(fallback_names="")).objects} == {f"object {i}" for i in NAMES}
    (root / "models" / "obj_000010.ply").unlink()
    with pytest.raises(SceneError, match=r"models/obj_000010\.ply: file not found"):
        read_bop(root)
