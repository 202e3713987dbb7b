"""Scene format: round trips, real capture readers, and errors that name the file."""
import json
import shutil

import numpy as np
import pytest

from conftest import need_rgbd
from rg_core.io.captures import read_capture, read_open3d_log, read_scene, write_open3d_log
from rg_core.io.images import SceneError, read_depth, write_depth
from rg_core.io.ply import read_ply, write_ply
from rg_core.io.scene import read_reasoninggd, transforms_dict


def test_depth_png_round_trip_and_invalid(tmp_path):
    d = np.array([[0.0, 0.5, 1.2345], [np.nan, -1.0, 70.0]], np.float32)
    write_depth(tmp_path / "d.png", d)
    back = read_depth(tmp_path / "d.png")
    np.testing.assert_allclose(back[0], d[0], atol=5.01e-4)   # rounded to the nearest mm
    assert np.all(back[1] == 0.0)  # NaN, negative and out-of-range (> 65.535 m) become invalid


def test_reasoninggd_round_trip(synth_scene_dir, synth_scene, tmp_path):
    s = synth_scene
    assert len(s.train) + len(s.test) == 16 and [f.index for f in s.test] == [0, 8]
    # Writing the frames back gives the same JSON content (poses, intrinsics, paths).
    for name, frames in (("transforms_train.json", s.train), ("transforms_test.json", s.test)):
        ours = transforms_dict(frames)
        disk = json.loads((synth_scene_dir / name).read_text())
        assert ours.keys() == disk.keys()
        np.testing.assert_allclose([f["transform_matrix"] for f in ours["frames"]],
                                   [f["transform_matrix"] for f in disk["frames"]], atol=1e-12)
        assert (ours["cx"], ours["cy"], ours["w"], ours["h"]) == (disk["cx"], disk["cy"], disk["w"], disk["h"])
    f = s.train[0]
    assert f.load_rgb().shape == (120, 160, 3)
    d = f.load_depth()
    assert d.dtype == np.float32 and 0.1 < np.median(d[d > 0]) < 6.0
    assert f.intrinsics.cx == pytest.approx(79.5) and f.intrinsics.cy == pytest.approx(59.5)
    assert {o.id for o in s.objects} == {1, 2, 3, 4, 5} == {q.object_id for q in s.queries}
    pts, cols = read_ply(synth_scene_dir / "points3d.ply")
    assert len(pts) > 1000 and cols.dtype == np.uint8


def test_ply_readable_by_open3d(tmp_path):
    import open3d as o3d

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    cols = rng.integers(0, 256, size=(100, 3)).astype(np.uint8)
    write_ply(tmp_path / "p.ply", pts, cols)
    pc = o3d.io.read_point_cloud(str(tmp_path / "p.ply"))
    np.testing.assert_allclose(np.asarray(pc.points), pts, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pc.colors) * 255, cols, atol=0.5)
    p2, c2 = read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_array_equal(c2, cols)


def test_open3d_log_round_trip_and_capture_with_log(tmp_path):
    root = need_rgbd("box_toys_50")
    s = read_capture(root)
    poses = {f.index: f.cam_to_world for f in s.frames}
    write_open3d_log(tmp_path / "traj.log", poses)
    back = read_open3d_log(tmp_path / "traj.log")
    assert back.keys() == poses.keys()
    for k in poses:
        np.testing.assert_allclose(back[k], poses[k], atol=1e-12)
    s2 = read_capture(root, trajectory=tmp_path / "traj.log")
    np.testing.assert_allclose(s2.frames[5].cam_to_world, s.frames[5].cam_to_world)


def test_capture_readers():
    s = read_scene(need_rgbd("box_toys_50"))
    assert s.kind == "capture" and len(s.frames) == 50 and len(s.test) == 7  # positions 0, 8, ..., 48
    f = s.frames[0]
    assert f.intrinsics.fx == pytest.approx(615.195, abs=1e-3) and (f.intrinsics.width, f.intrinsics.height) == (640, 480)
    assert f.load_rgb().shape == (480, 640, 3)
    d = f.load_depth()
    assert 0.2 < np.median(d[d > 0]) < 2.0
    k = read_scene(need_rgbd("redkitchen_100"))
    assert len(k.frames) == 100 and k.frames[0].intrinsics.fx == 585.0
    assert k.frames[0].image_path.suffix == ".jpg"


# ---------------------------------------------------------------------------------------- bad input

@pytest.fixture
def scene_copy(synth_scene_dir, tmp_path):
    dst = tmp_path / "scene"
    shutil.copytree(synth_scene_dir, dst)
    return dst


def _edit_json(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def test_missing_image_names_the_file(scene_copy):
    (scene_copy / "images" / "0003.png").unlink()
    with pytest.raises(SceneError, match=r"images/0003.png: file not found"):
        read_reasoninggd(scene_copy)


def test_missing_transforms(scene_copy):
    (scene_copy / "transforms_train.json").unlink()
    with pytest.raises(SceneError, match="transforms_train.json: file not found"):
        read_reasoninggd(scene_copy)
    with pytest.raises(SceneError, match="not a scene folder"):
        read_scene(scene_copy)


def test_non_rigid_pose_is_rejected(scene_copy):
    def skew(d):
        d["frames"][2]["transform_matrix"][0][0] = 1.7
    _edit_json(scene_copy / "transforms_train.json", skew)
    with pytest.raises(SceneError, match=r"transforms_train.json: frames\[2\]: rotation is not orthonormal"):
        read_reasoninggd(scene_copy)


def test_missing_key_and_bad_json(scene_copy):
    _edit_json(scene_copy / "transforms_test.json", lambda d: d.pop("fl_x"))
    with pytest.raises(SceneError, match="transforms_test.json: missing key 'fl_x'"):
        read_reasoninggd(scene_copy)
    (scene_copy / "transforms_test.json").write_text("{oops")
    with pytest.raises(SceneError, match="transforms_test.json: not valid JSON"):
        read_reasoninggd(scene_copy)


def test_wrong_image_size_names_the_file(scene_copy):
    from rg_core.io.images import write_rgb

    write_rgb(scene_copy / "images" / "0001.png", np.zeros((10, 12, 3), np.uint8))
    s = read_reasoninggd(scene_copy)
    fr = next(f for f in s.frames if f.index == 1)
    with pytest.raises(SceneError, match=r"images/0001.png: image is 12x10, expected 160x120"):
        fr.load_rgb()


def test_depth_in_wrong_unit(scene_copy):
    # Depth written in metres into a millimetre PNG: median far below 1 cm.
    s = read_reasoninggd(scene_copy)
    fr = s.train[0]
    d = fr.load_depth()
    write_depth(fr.depth_path, d, depth_scale=1.0)
    with pytest.raises(SceneError, match=r"depth/0001.png: median depth .* outside \[0.01, 50\] m"):
        fr.load_depth()
    # ... and a scene claiming micrometres reads as kilometres' worth of millimetres: too far.
    _edit_json(scene_copy / "transforms_test.json", lambda j: j.update(depth_scale=0.01))
    s = read_reasoninggd(scene_copy)
    with pytest.raises(SceneError, match="wrong depth unit"):
        s.test[0].load_depth()


def test_depth_not_uint16(scene_copy):
    import cv2

    cv2.imwrite(str(scene_copy / "depth" / "0002.png"), np.zeros((120, 160), np.uint8))
    fr = next(f for f in read_reasoninggd(scene_copy).frames if f.index == 2)
    with pytest.raises(SceneError, match=r"depth/0002.png: depth must be a single-channel uint16 PNG"):
        fr.load_depth()


def test_bad_capture_folder(tmp_path):
    root = need_rgbd("box_toys_50")
    dst = tmp_path / "cap"
    shutil.copytree(root, dst)
    (dst / "frame-000021.pose.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(SceneError, match=r"frame-000021.pose.txt: expected a 4x4 matrix"):
        read_capture(dst)
    (dst / "frame-000021.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (dst / "frame-000023.depth.png").unlink()
    with pytest.raises(SceneError, match=r"frame-000023.depth.png: file not found"):
        read_capture(dst)
    bad_log = tmp_path / "t.log"
    bad_log.write_text("0 0 1\n1 0 0 0\n0 1 0 0\n")
    with pytest.raises(SceneError, match="multiple of 5"):
        read_open3d_log(bad_log)


def test_ycb_reader():
    from rg_core.io.ycb import read_ycb, ycb_class_name

    classes, frames = read_ycb(need_rgbd("ycb_video_3"))
    assert len(classes) == 21 and classes[4] == "mustard bottle" and ycb_class_name("025_mug") == "mug"
    assert len(frames) == 3
    f = frames[0]
    assert f.rgb.shape == (480, 640, 3) and f.K[0, 0] == pytest.approx(1066.8, abs=0.5)
    assert 0.3 < float(np.median(f.depth[f.depth > 0])) < 3.0  # factor 10000 read as metres
    assert set(f.class_ids) <= set(np.unique(f.label).tolist()) and f.class_ids


def test_ycb_sequence_reads_as_a_posed_scene_with_ground_truth(tmp_path):
    """rotation_translation_matrix is world -> camera: the objects' meta.mat poses, taken to the
    world with our camera poses, stay put across the views (they do not move in this sequence)."""
    import scipy.io

    root = need_rgbd("ycb_video_3")
    s = read_scene(root)
    assert s.kind == "ycb" and [f.index for f in s.test] == [1] and [f.index for f in s.train] == [5, 9]
    assert [(o.id, o.name) for o in s.objects] == [(8, "gelatin box"), (14, "mug"), (21, "foam brick")]
    assert all(q.implicit for q in s.queries)   # the description set covers them
    centres = []
    for f in s.frames:
        poses = scipy.io.loadmat(str(root / f"{f.index:06d}-meta.mat"))["poses"]   # [3, 4, N] model -> camera
        centres.append(np.stack([f.cam_to_world[:3, :3] @ poses[:, 3, k] + f.cam_to_world[:3, 3]
                                 for k in range(poses.shape[2])]))
    assert np.abs(np.stack(centres) - centres[0]).max() < 0.002
    for o, c in zip(s.objects, centres[0]):   # each box holds its object's origin, and is object-sized
        size = np.subtract(o.aabb_max, o.aabb_min)
        assert np.all(np.asarray(o.aabb_min) - 0.01 < c) and np.all(c < np.asarray(o.aabb_max) + 0.01), o.name
        assert np.all((0.02 < size) & (size < 0.15)), (o.name, size)
    f = s.test[0]
    assert not f.has_amodal_masks() and set(np.unique(f.load_visible_mask())) == {0, 8, 14, 21}
    with pytest.raises(SceneError, match="no amodal masks"):
        f.load_complete_mask(8)
    # A meta.mat without camera poses is named, with what is missing.
    bad = tmp_path / "seq"
    shutil.copytree(root, bad)
    meta = scipy.io.loadmat(str(bad / "000005-meta.mat"))
    del meta["rotation_translation_matrix"]
    scipy.io.savemat(str(bad / "000005-meta.mat"), {k: v for k, v in meta.items() if not k.startswith("__")})
    with pytest.raises(SceneError, match="000005-meta.mat: missing rotation_translation_matrix"):
        read_scene(bad)
