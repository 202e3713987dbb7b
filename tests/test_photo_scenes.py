"""Photo-only scenes (issue 63): COLMAP models (text and binary, five camera models), nerfstudio's
transforms.json, LLFF's poses_bounds.npy, ReasoningGD frames without depth. The files are written
here from their formats' definitions (COLMAP's text format by hand, its binary by pycolmap), not by
the readers' code; poses come back to 1e-6 and distorted photos land where the pinhole camera puts
them."""
from __future__ import annotations

import json
import re
import shutil

import cv2
import numpy as np
import pytest

from rg_core.config import PhotoMapConfig
from rg_core.geometry.conventions import project
from rg_core.geometry.rotations import rot_to_quat
from rg_core.io.captures import read_scene, scene_kind
from rg_core.io.images import SceneError, read_rgb, write_rgb
from rg_core.io.scene import NO_DEPTH, read_reasoninggd

pycolmap = pytest.importorskip("pycolmap")
AS_IS = PhotoMapConfig(world_scale=1.0)   # the readers' own units (read_scene's scale rule: test_world_scale.py)


# --------------------------------------------------------------------------- writers (the formats' definitions)

def colmap_text(d, cameras, images, points=()):
    """cameras [(id, model, w, h, params)], images [(id, R_w2c, t_w2c, camera id, name)],
    points [(id, xyz, rgb)] -> COLMAP's text model in folder d (quaternion w, x, y, z)."""
    d.mkdir(parents=True, exist_ok=True)
    (d / "cameras.txt").write_text("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
        f"{i} {m} {w} {h} {' '.join(repr(float(p)) for p in ps)}\n" for i, m, w, h, ps in cameras))
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"]
    for i, R, t, cam, name in images:
        x, y, z, w = rot_to_quat(R)
        nums = " ".join(repr(float(v)) for v in (w, x, y, z, *t))
        lines.append(f"{i} {nums} {cam} {name}\n\n")
    (d / "images.txt").write_text("".join(lines))
    (d / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(
        f"{i} {' '.join(repr(float(v)) for v in p)} {c[0]} {c[1]} {c[2]} 0.5\n" for i, p, c in points))


def w2c_of(c2w):
    w2c = np.linalg.inv(c2w)
    return w2c[:3, :3], w2c[:3, 3]


def scene_as_colmap(scene, root, binary=False):
    """The frames of a ReasoningGD scene as a COLMAP model (PINHOLE, principal point +0.5: COLMAP's
    pixel centres are at .5) with the photos in images/."""
    (root / "images").mkdir(parents=True)
    intr = scene.frames[0].intrinsics
    images = []
    for f in scene.frames:
        shutil.copy(f.image_path, root / "images" / f.image_path.name)
        images.append((f.index + 1, *w2c_of(f.cam_to_world), 1, f.image_path.name))
    pts = [(1, (0.1, 0.2, 0.3), (10, 20, 30)), (2, (-1.0, 0.5, 2.0), (200, 100, 0))]
    txt = root / ("sparse_txt" if binary else "sparse/0")
    colmap_text(txt, [(1, "PINHOLE", intr.width, intr.height, [intr.fx, intr.fy, intr.cx + 0.5, intr.cy + 0.5])],
                images, pts)
    if binary:   # pycolmap's own writer
        (root / "sparse" / "0").mkdir(parents=True)
        pycolmap.Reconstruction(str(txt)).write_binary(str(root / "sparse" / "0"))
        shutil.rmtree(txt)
    return root


def assert_same_frames(got, want):
    assert [f.image_path.name for f in got] == [f.image_path.name for f in want]
    for a, b in zip(got, want):
        np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=1e-6)


# --------------------------------------------------------------------------- COLMAP

@pytest.mark.parametrize("binary", [False, True])
def test_colmap_round_trip_gives_back_the_poses(synth_scene, tmp_path, binary):
    root = scene_as_colmap(synth_scene, tmp_path / "c", binary)
    assert scene_kind(root) == "colmap"
    s = read_scene(root, photo=AS_IS)
    assert s.kind == "colmap" and len(s.frames) == len(synth_scene.frames)
    assert_same_frames(s.frames, synth_scene.frames)
    a, b = s.frames[3].intrinsics, synth_scene.frames[3].intrinsics
    np.testing.assert_allclose(a.K, b.K, atol=1e-9)
    assert [f.index for f in s.test] == [0, 8] and len(s.train) == 14   # every 8th image
    assert all(f.depth_path is None and f.undistort is None for f in s.frames)
    np.testing.assert_array_equal(s.frames[2].load_rgb(), read_rgb(synth_scene.frames[2].image_path))
    pts = s.load_points()
    order = np.argsort(pts.xyz[:, 0])
    np.testing.assert_allclose(pts.xyz[order], [(-1.0, 0.5, 2.0), (0.1, 0.2, 0.3)])
    np.testing.assert_array_equal(pts.rgb[order], [(200, 100, 0), (10, 20, 30)])


def test_colmap_pose_convention_on_known_values(tmp_path):
    """qvec (w, x, y, z) and tvec are world-to-camera: a camera rotated 90 deg about its z axis,
    2 m in front of the origin, sees the world point (0, 0, 0) at its principal point and the point
    (0.1, 0, 0) below it (image y grows downward)."""
    root = tmp_path / "c"
    (root / "images").mkdir(parents=True)
    write_rgb(root / "images" / "a.png", np.zeros((40, 60, 3), np.uint8))
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # camera from world
    colmap_text(root / "sparse" / "0", [(7, "SIMPLE_PINHOLE", 60, 40, [50.0, 30.5, 20.5])],
                [(3, R, np.array([0.0, 0.0, 2.0]), 7, "a.png")])
    f = read_scene(root, photo=AS_IS).frames[0]
    np.testing.assert_allclose(f.cam_to_world[:3, 3], [0.0, 0.0, -2.0], atol=1e-12)
    np.testing.assert_allclose(f.cam_to_world[:3, :3], R.T, atol=1e-12)
    assert (f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy) == (50.0, 50.0, 30.0, 20.0)
    uv, z = project(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]), f.intrinsics.K, f.cam_to_world)
    np.testing.assert_allclose(uv, [[30.0, 20.0], [30.0, 22.5]], atol=1e-9)
    np.testing.assert_allclose(z, [2.0, 2.0])


def _distort(model, params, xy):
    """COLMAP's camera models on normalised points xy [N, 2] -> pixels [N, 2] (COLMAP coordinates:
    the top-left pixel's centre is (0.5, 0.5)), written from COLMAP's definitions."""
    x, y = xy[:, 0], xy[:, 1]
    f = dict(zip({"SIMPLE_PINHOLE": "f cx cy", "PINHOLE": "fx fy cx cy", "SIMPLE_RADIAL": "f cx cy k",
                  "RADIAL": "f cx cy k1 k2", "OPENCV": "fx fy cx cy k1 k2 p1 p2"}[model].split(), params))
    fx, fy = f.get("fx", f.get("f")), f.get("fy", f.get("f"))
    k1, k2, p1, p2 = f.get("k1", f.get("k", 0.0)), f.get("k2", 0.0), f.get("p1", 0.0), f.get("p2", 0.0)
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2
    dx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    dy = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    return np.stack([fx * (x + dx) + f["cx"], fy * (y + dy) + f["cy"]], 1)


CAMERAS = {
    "SIMPLE_PINHOLE": [80.0, 60.0, 45.0],
    "PINHOLE": [82.0, 78.0, 61.0, 44.0],
    "SIMPLE_RADIAL": [80.0, 60.0, 45.0, -0.12],
    "RADIAL": [80.0, 59.0, 46.0, -0.10, 0.03],
    "OPENCV": [82.0, 78.0, 61.0, 44.0, -0.08, 0.02, 0.004, -0.003],
}


@pytest.mark.parametrize("model", list(CAMERAS))
def test_each_camera_model_lands_on_the_pinhole_projection(tmp_path, model):
    """A dot drawn where the distorted model puts a point is, in the image the frame loads, where
    the frame's pinhole intrinsics project it (and so are the undistorted points)."""
    params = CAMERAS[model]
    W, H = 120, 90
    xy = np.array([[0.0, 0.0], [0.25, -0.2], [-0.3, 0.2], [0.3, 0.22]])   # normalised camera coordinates
    px = _distort(model, params, xy) - 0.5                                   # OpenCV pixel coordinates
    root = tmp_path / model
    (root / "images").mkdir(parents=True)
    yy, xx = np.mgrid[0:H, 0:W]
    for i, (u, v) in enumerate(px):   # one photo per point: a Gaussian dot, sigma 1.5 px
        img = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.5 ** 2))
        write_rgb(root / "images" / f"{i}.png", np.repeat((255 * img).astype(np.uint8)[..., None], 3, 2))
    colmap_text(root / "sparse" / "0", [(1, model, W, H, params)],
                [(i + 1, np.eye(3), np.zeros(3), 1, f"{i}.png") for i in range(len(xy))])
    s = read_scene(root, photo=AS_IS)
    assert (s.frames[0].undistort is None) == (model in ("SIMPLE_PINHOLE", "PINHOLE"))
    for f, (x, y) in zip(s.frames, xy):
        K = f.intrinsics.K
        want = np.array([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]])
        img = f.load_rgb()[..., 0].astype(np.float64)
        img[img < 40] = 0   # the dot, not the rest of the Gaussian's tail
        ys, xs = np.nonzero(img)
        got = np.array([(xs * img[ys, xs]).sum(), (ys * img[ys, xs]).sum()]) / img[ys, xs].sum()
        np.testing.assert_allclose(got, want, atol=0.25)
        if f.undistort is not None:
            np.testing.assert_allclose(f.undistort.points(px[int(f.image_path.stem)][None])[0], want, atol=1e-3)
    if model == "SIMPLE_PINHOLE":
        assert s.frames[0].intrinsics.K.tolist() == [[80.0, 0.0, 59.5], [0.0, 80.0, 44.5], [0.0, 0.0, 1.0]]


def test_colmap_errors_say_what_is_wrong_and_what_was_expected(tmp_path):
    root = tmp_path / "c"
    (root / "images").mkdir(parents=True)
    write_rgb(root / "images" / "a.png", np.zeros((40, 60, 3), np.uint8))
    from rg_core.io.colmap import read_colmap

    with pytest.raises(SceneError, match=r"no COLMAP sparse model \(expected .*sparse/0/ or .*sparse/ with cameras, "
                                         r"images and points3D"):
        read_colmap(root)
    colmap_text(root / "sparse" / "0", [(1, "FULL_OPENCV", 60, 40, [50, 50, 30, 20] + [0.01] * 8)],
                [(1, np.eye(3), np.zeros(3), 1, "a.png")])
    with pytest.raises(SceneError, match="camera model FULL_OPENCV is not supported; supported: SIMPLE_PINHOLE, "
                                         "PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV"):
        read_colmap(root)
    colmap_text(root / "sparse" / "0", [(1, "PINHOLE", 60, 40, [50, 50, 30, 20])],
                [(1, np.eye(3), np.zeros(3), 1, "a.png"), (2, np.eye(3), np.ones(3), 1, "b.png")])
    with pytest.raises(SceneError, match=r"images/b.png: file not found \(image 2 of"):
        read_colmap(root)
    (root / "sparse" / "0" / "points3D.txt").unlink()
    with pytest.raises(SceneError, match="no COLMAP sparse model"):
        read_colmap(root)
    from rg_core.io.colmap import read_model

    with pytest.raises(SceneError, match=r"expected cameras, images and points3D, all .bin or all .txt; found "
                                         r"\['cameras.txt', 'images.txt'\]"):
        read_model(root / "sparse" / "0")


def test_downscaled_photos_scale_the_camera(synth_scene, tmp_path):
    root = scene_as_colmap(synth_scene, tmp_path / "c")
    for p in (root / "images").iterdir():   # half-size copies of the photos COLMAP saw
        write_rgb(p, cv2.resize(read_rgb(p), (80, 60), interpolation=cv2.INTER_AREA))
    f = read_scene(root, photo=AS_IS).frames[0]
    b = synth_scene.frames[0].intrinsics
    assert (f.intrinsics.width, f.intrinsics.height) == (80, 60) and f.load_rgb().shape == (60, 80, 3)
    assert f.intrinsics.fx == pytest.approx(b.fx / 2) and f.intrinsics.cx == pytest.approx((b.cx + 0.5) / 2 - 0.5)


# --------------------------------------------------------------------------- nerfstudio

def scene_as_nerfstudio(scene, root, **extra):
    (root / "images").mkdir(parents=True)
    intr = scene.frames[0].intrinsics
    frames = []
    for f in reversed(scene.frames):   # any order in the file: frames are taken in file_path order
        shutil.copy(f.image_path, root / "images" / f.image_path.name)
        gl = f.cam_to_world.copy()
        gl[:3, 1:3] *= -1             # OpenCV camera axes -> OpenGL's (y up, z backward)
        frames.append({"file_path": f"images/{f.image_path.name}", "transform_matrix": gl.tolist()})
    data = {"camera_model": "OPENCV", "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx + 0.5, "cy": intr.cy + 0.5,
            "w": intr.width, "h": intr.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames, **extra}
    (root / "transforms.json").write_text(json.dumps(data))
    return root


def test_nerfstudio_round_trip_and_axes(synth_scene, tmp_path):
    root = scene_as_nerfstudio(synth_scene, tmp_path / "n")
    assert scene_kind(root) == "nerfstudio"
    s = read_scene(root, photo=AS_IS)
    assert s.kind == "nerfstudio"
    assert_same_frames(s.frames, synth_scene.frames)
    np.testing.assert_allclose(s.frames[0].intrinsics.K, synth_scene.frames[0].intrinsics.K, atol=1e-9)
    assert [f.index for f in s.test] == [0, 8] and all(f.depth_path is None for f in s.frames)
    # the identity transform_matrix is a camera looking down the world's -z with y up
    data = json.loads((root / "transforms.json").read_text())
    data["frames"][0]["transform_matrix"] = np.eye(4).tolist()
    (root / "transforms.json").write_text(json.dumps(data))
    f = next(f for f in read_scene(root, photo=AS_IS).frames if f.image_path.name == data["frames"][0]["file_path"][7:])
    np.testing.assert_allclose(f.cam_to_world[:3, :3], np.diag([1.0, -1.0, -1.0]))


def test_nerfstudio_split_points_and_errors(synth_scene, tmp_path):
    names = [f"images/{f.image_path.name}" for f in synth_scene.frames]
    A = [[1.0, 0.0, 0.0, 0.5], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]]   # nerfstudio's new-from-COLMAP world
    root = scene_as_nerfstudio(synth_scene, tmp_path / "n", test_filenames=names[1:3], applied_transform=A)
    colmap_text(root / "colmap" / "sparse" / "0", [(1, "PINHOLE", 160, 120, [100, 100, 80, 60])], [],
                [(1, (1.0, 2.0, 3.0), (1, 2, 3))])
    s = read_scene(root, photo=AS_IS)
    assert [f.image_path.name for f in s.test] == [n[7:] for n in names[1:3]] and len(s.train) == len(names) - 2
    np.testing.assert_allclose(s.load_points().xyz, [[1.5, 3.0, -2.0]])   # moved into the poses' world
    data = json.loads((root / "transforms.json").read_text())
    data["frames"][4]["file_path"] = "images/missing.png"
    (root / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(SceneError, match=r"images/missing.png: image not found \(file_path of frames\[4\]"):
        read_scene(root, photo=AS_IS)
    data["frames"][4]["file_path"] = names[0]
    data["camera_model"] = "OPENCV_FISHEYE"
    (root / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(SceneError, match="camera_model OPENCV_FISHEYE is not supported; supported: SIMPLE_PINHOLE"):
        read_scene(root, photo=AS_IS)


def test_nerfstudio_distorted_frames_undistort_at_load(synth_scene, tmp_path):
    root = scene_as_nerfstudio(synth_scene, tmp_path / "n", k1=-0.1, p1=0.002)
    f = read_scene(root, photo=AS_IS).frames[0]
    assert f.undistort is not None and f.load_rgb().shape == (120, 160, 3)
    np.testing.assert_allclose(f.undistort.dist, [-0.1, 0.0, 0.002, 0.0, 0.0])


# --------------------------------------------------------------------------- LLFF

def scene_as_llff(scene, root, near_far=(0.2, 5.0)):
    """poses_bounds.npy from its definition: per image [R | t | hwf] with the rotation's columns
    in LLFF's order (down, right, backwards), row-major, then near and far."""
    (root / "images").mkdir(parents=True)
    rows = []
    for f in scene.frames:
        shutil.copy(f.image_path, root / "images" / f.image_path.name)
        c = f.cam_to_world
        m = np.stack([c[:3, 1], c[:3, 0], -c[:3, 2], c[:3, 3],
                      [f.intrinsics.height, f.intrinsics.width, f.intrinsics.fx]], 1)   # [3, 5]
        rows.append(np.concatenate([m.reshape(-1), near_far]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    return root


def test_llff_round_trip_and_axes(synth_scene, tmp_path):
    root = scene_as_llff(synth_scene, tmp_path / "l")
    assert scene_kind(root) == "llff"
    s = read_scene(root, photo=AS_IS)
    assert s.kind == "llff" and s.labels is None and [f.index for f in s.test] == [0, 8]
    assert_same_frames(s.frames, synth_scene.frames)
    f, b = s.frames[0], synth_scene.frames[0]
    assert f.intrinsics.fx == pytest.approx(b.intrinsics.fx) and f.intrinsics.cx == pytest.approx(79.5) and f.bounds == (0.2, 5.0)
    from rg_core.io.llff import opencv_from_llff

    # LLFF's (down, right, back) = world (x, y, z): OpenCV's right is world y, down world x, forward -z
    np.testing.assert_allclose(opencv_from_llff(np.eye(3, 4))[:3, :3], [[0, 1, 0], [1, 0, 0], [0, 0, -1]])


def test_llff_downscaled_copies(synth_scene, tmp_path):
    root = scene_as_llff(synth_scene, tmp_path / "l")
    (root / "images").rename(root / "images_4")   # 3D-OVS-style: only the downscaled copies
    for p in (root / "images_4").iterdir():
        write_rgb(p, cv2.resize(read_rgb(p), (40, 30), interpolation=cv2.INTER_AREA))
    f = read_scene(root, photo=AS_IS).frames[5]
    assert f.image_path.parent.name == "images_4" and f.load_rgb().shape == (30, 40, 3)
    assert f.intrinsics.fx == pytest.approx(synth_scene.frames[5].intrinsics.fx / 4) and f.intrinsics.cx == 19.5
    np.testing.assert_allclose(f.cam_to_world, synth_scene.frames[5].cam_to_world, atol=1e-6)


def test_llff_errors(synth_scene, tmp_path):
    root = scene_as_llff(synth_scene, tmp_path / "l")
    (root / "images" / "0003.png").unlink()
    with pytest.raises(SceneError, match=r"poses_bounds.npy: 16 poses, but .*images holds 15 images"):
        read_scene(root, photo=AS_IS)
    np.save(root / "poses_bounds.npy", np.zeros((15, 15)))
    with pytest.raises(SceneError, match=r"expected a finite \[N, 17\] array"):
        read_scene(root, photo=AS_IS)


# --------------------------------------------------------------------------- scenes without depth

def test_reasoninggd_without_depth_reads_as_frames_without_depth(synth_scene_dir, tmp_path):
    """Frames without depth_file_path have depth_path None; what needs a depth image says why it
    has none (mapping such scenes is issue 63's RGB-only mapping, rg_core/map/)."""
    root = tmp_path / "s"
    shutil.copytree(synth_scene_dir, root)
    shutil.rmtree(root / "depth")
    for name in ("transforms_train.json", "transforms_test.json"):
        data = json.loads((root / name).read_text())
        for fr in data["frames"]:
            del fr["depth_file_path"]
        (root / name).write_text(json.dumps(data))
    s = read_reasoninggd(root)
    assert all(f.depth_path is None for f in s.frames) and not s.has_depth() and s.objects
    assert s.load_points().xyz.shape[1] == 3
    with pytest.raises(SceneError, match=re.escape(f"frame 1 (0001.png): {NO_DEPTH}")):
        s.train[0].load_depth()
    with pytest.raises(SceneError, match=re.escape(f"{NO_DEPTH} (14 of 14 training frames have none, e.g. 0001.png)")):
        s.require_depth()
    from rg_core.io.scene import depth_or_none

    assert depth_or_none(s.test[0]) is None   # rg eval's test views: masks follow the render alone
