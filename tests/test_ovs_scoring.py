"""The benchmarks' own scoring (issue 63): LangSplat's LERF-OVS 2D protocol against a reference
written here from its description (plain loops, no OpenCV), on a case with a known answer; the
LERF-OVS label reader on files of the real schema written by hand; 3D-OVS segmentations and
their argmax mIoU; both protocols over a grounded map; `rg eval` printing them."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from rg_core.eval.ovs import (LangSplatRule, argmax_segmentation, evaluate_labels, langsplat_localized,
                              langsplat_mask, majority_vote, mean_filter)
from rg_core.io.images import SceneError, write_mask, write_rgb
from rg_core.io.ovs_labels import parse_lerf_label, read_3dovs_segmentations, read_lerf_labels
from rg_core.io.scene import Frame, Intrinsics, Scene
from rg_core.io.splits import labelled_split


# --------------------------------------------------------------------------- the reference (LangSplat's description)

def ref_mean(x, k):
    """k x k mean; the window of pixel i spans i - k//2 .. i + k - k//2 - 1; outside the image the
    image is mirrored about its edge pixel (..., 2, 1, 0, 1, 2, ...)."""
    def mirror(i, n):
        while i < 0 or i >= n:
            i = -i if i < 0 else 2 * (n - 1) - i
        return i

    def along(a, axis):
        n = a.shape[axis]
        out = np.empty_like(a)
        for i in range(n):
            idx = [mirror(j, n) for j in range(i - k // 2, i + k - k // 2)]
            if axis == 0:
                out[i] = a[idx].mean(0)
            else:
                out[:, i] = a[:, idx].mean(1)
        return out

    return along(along(np.asarray(x, np.float64), 1), 0)


def ref_vote(mask, r):
    """Each pixel takes the majority of the (2r+1)^2 window around it, cut at the border; a tie: 0."""
    H, W = mask.shape
    out = np.zeros_like(mask, bool)
    for y in range(H):
        for x in range(W):
            win = mask[max(0, y - r): y + r + 1, max(0, x - r): x + r + 1]
            out[y, x] = win.sum() * 2 > win.size
    return out


def ref_2d(levels, gt, boxes, k=30, thr=0.4, r=3):
    """LangSplat's scorer as its paper and evaluation describe it -> (IoU, localized)."""
    smoothed = [(lv + ref_mean(lv, k)) / 2 for lv in levels]
    s = smoothed[int(np.argmax([m.max() for m in smoothed]))]           # the level that peaks highest
    n = (s - s.min()) / (s.max() - s.min() + 1e-9)                      # min-max normalised
    pred = ref_vote(np.clip(2 * n - 1, 0, 1) > thr, r)                  # on [-1, 1], clipped, thresholded
    iou = (pred & gt).sum() / (pred | gt).sum()
    filt = [ref_mean(lv, k) for lv in levels]
    f = filt[int(np.argmax([m.max() for m in filt]))]
    ys, xs = np.nonzero(f == f.max())
    loc = any(((xs >= x1) & (xs <= x2) & (ys >= y1) & (ys <= y2)).any() for x1, y1, x2, y2 in boxes)
    return float(iou), bool(loc)


def lib_2d(levels, gt, boxes, rule=LangSplatRule()):
    mask, _ = langsplat_mask(levels, rule)
    inter, union = (mask & gt).sum(), (mask | gt).sum()
    return float(inter / union), langsplat_localized(levels, boxes, rule)[0]


def test_filters_equal_the_reference():
    rng = np.random.default_rng(0)
    x = rng.random((37, 45))
    for k in (1, 4, 5, 30):
        np.testing.assert_allclose(mean_filter(x, k), ref_mean(x, k), atol=1e-12)
    m = rng.random((23, 31)) > 0.5
    for r in (0, 1, 3):
        np.testing.assert_array_equal(majority_vote(m, r), ref_vote(m, r) if r else m)


def test_2d_protocol_known_answer():
    """Two categories on 64x48 relevancy maps of two levels, steps across x. Category A: its first
    level (1 left of x = 24) peaks highest and the rule keeps exactly x < 24; its mask is x < 32:
    IoU 24/32. Category B: the second level (0.9 right of x = 48) beats the first (0.6), the mask
    is x >= 48 and so is B's: IoU 1. mIoU 87.5. Localization: A's filtered peak (x <= 8) lies in its
    box x <= 20, B's (x = 63) not in its box x <= 10: 50 %."""
    H, W = 48, 64
    x = np.broadcast_to(np.arange(W), (H, W))
    left, right = (x < 24).astype(float), (x >= 48).astype(float)
    cases = {"A": (np.stack([left, 0.5 * right]), x < 32, [[0, 0, 20, 47]]),
             "B": (np.stack([0.6 * left, 0.9 * right]), x >= 48, [[0, 0, 10, 47]])}
    got = {c: lib_2d(lv, gt, b) for c, (lv, gt, b) in cases.items()}
    ref = {c: ref_2d(lv, gt, b) for c, (lv, gt, b) in cases.items()}
    assert got == ref
    assert got["A"] == (pytest.approx(0.75), True) and got["B"] == (pytest.approx(1.0), False)
    assert np.mean([got[c][0] for c in got]) == pytest.approx(0.875)
    assert langsplat_mask(cases["B"][0])[1] == 1


def test_2d_protocol_equals_the_reference_on_random_maps():
    rng = np.random.default_rng(3)
    H, W = 40, 52
    yy, xx = np.mgrid[0:H, 0:W]
    for _ in range(4):
        levels = []
        for _ in range(3):
            m = 0.05 * rng.random((H, W))
            for _ in range(3):
                cx, cy, s, a = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(3, 10), rng.uniform(0.2, 1.0)
                m += a * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
            levels.append(m)
        gt = (xx - rng.uniform(10, 40)) ** 2 + (yy - rng.uniform(10, 30)) ** 2 < rng.uniform(40, 200)
        boxes = [[rng.uniform(0, 30), rng.uniform(0, 20), rng.uniform(30, 52), rng.uniform(20, 40)]]
        for rule in (LangSplatRule(), LangSplatRule(kernel=9, vote=1)):
            got = lib_2d(np.stack(levels), gt, boxes, rule)
            want = ref_2d(levels, gt, boxes, rule.kernel, rule.threshold, rule.vote)
            assert got[0] == pytest.approx(want[0], abs=1e-12) and got[1] == want[1]


# --------------------------------------------------------------------------- LERF-OVS label files

LABEL = {"info": {"name": "frame_00002.jpg", "width": 64, "height": 48},
         "objects": [
             {"category": "rubber duck", "group": 1, "segmentation": [[10, 10], [19, 10], [19, 19], [10, 19]],
              "bbox": [10, 10, 19, 19], "area": 100, "iscrowd": 0},
             {"category": "rubber duck", "group": 2, "segmentation": [[30.7, 5.2], [39.9, 5.0], [39.0, 9.8], [30.0, 9.0]],
              "bbox": [30, 5, 39, 9], "area": 50, "iscrowd": 0},
             {"category": "mug", "group": 3, "segmentation": [[40, 30], [50, 30], [45, 40]],
              "bbox": [40, 30, 50, 40], "area": 55, "iscrowd": 0}]}


def frames_of(root, n=4, size=(64, 48)):
    intr = Intrinsics(50.0, 50.0, size[0] / 2 - 0.5, size[1] / 2 - 0.5, *size)
    out = []
    for i in range(n):
        p = root / "images" / f"frame_{i + 1:05d}.jpg"
        write_rgb(p, np.zeros((size[1], size[0], 3), np.uint8))
        c2w = np.eye(4)
        c2w[0, 3] = 0.1 * i
        out.append(Frame(index=i, intrinsics=intr, cam_to_world=c2w, image_path=p))
    return out


def test_lerf_label_reader_on_the_real_schema(tmp_path):
    frames = frames_of(tmp_path)
    (tmp_path / "label").mkdir()
    (tmp_path / "label" / "frame_00002.json").write_text(json.dumps(LABEL))
    labels = read_lerf_labels(tmp_path / "label", frames)
    assert labels.benchmark == "lerf_ovs" and labels.classes == ["mug", "rubber duck"]
    (v,) = labels.views
    assert v.frame is frames[1] and v.size == (64, 48) and v.categories == ["rubber duck", "mug"]
    m = v.masks()
    duck = np.zeros((48, 64), bool)
    duck[10:20, 10:20] = True   # fillPoly fills the outline's pixels too; vertices truncated to whole pixels
    duck[5:10, 30:40] = True
    np.testing.assert_array_equal(m["rubber duck"], duck)   # the two objects of the category, unioned
    mug = m["mug"]
    assert mug[33, 45] and mug[30, 40] and not mug[39, 40] and mug[:, :40].sum() == 0 and mug[41:].sum() == 0
    np.testing.assert_allclose(v.frame_boxes()["rubber duck"], [[10, 10, 19, 19], [30, 5, 39, 9]])
    train, test = labelled_split(frames, labels)
    assert test == [frames[1]] and len(train) == 4                  # benchmarks train on every image
    train, test = labelled_split(frames, labels, labelled_in_train=False)
    assert test == [frames[1]] and [f.index for f in train] == [0, 2, 3]
    # photos at half the labels' size: masks and boxes follow (pixel centres scale)
    small = frames_of(tmp_path / "small", size=(32, 24))
    v2 = read_lerf_labels(tmp_path / "label", small).views[0]
    assert v2.masks()["rubber duck"].shape == (24, 32) and v2.masks()["rubber duck"].sum() == 25 + 10
    np.testing.assert_allclose(v2.frame_boxes()["mug"], [[19.75, 14.75, 24.75, 19.75]])


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["objects"][2].update(segmentation=[[40, 30], [50, 30]]),
     r"objects\[2\] \('mug'\): the polygon has 2 point\(s\), at least 3 are needed"),
    (lambda d: d["objects"][0].update(segmentation=[[1, 2, 3], [4, 5, 6], [7, 8, 9]]),
     r"objects\[0\] \('rubber duck'\): 'segmentation' must be a polygon \[\[x, y\], \.\.\.\]"),
    (lambda d: d["objects"][1].update(bbox=[1, 2, 3]), r"objects\[1\] \('rubber duck'\): 'bbox' must be \[x1, y1, x2, y2\]"),
    (lambda d: d["objects"][1].pop("category"), r"objects\[1\]: needs a non-empty 'category'"),
    (lambda d: d.pop("info"), r"expected \{\"info\": \{\"name\", \"width\", \"height\"\}, \"objects\": \[\.\.\.\]\}"),
    (lambda d: d["info"].update(width=0), r"info needs a non-empty 'name' and positive integer 'width' and 'height'"),
])
def test_bad_label_files_name_what_is_wrong(tmp_path, edit, match):
    d = json.loads(json.dumps(LABEL))
    edit(d)
    (tmp_path / "frame_00002.json").write_text(json.dumps(d))
    with pytest.raises(SceneError, match=r"frame_00002.json: " + match):
        parse_lerf_label(tmp_path / "frame_00002.json")


def test_a_label_for_an_image_the_scene_lacks(tmp_path):
    frames = frames_of(tmp_path, n=2)
    (tmp_path / "label").mkdir()
    (tmp_path / "label" / "frame_00009.json").write_text(json.dumps({**LABEL, "info": {**LABEL["info"], "name": "frame_00009.jpg"}}))
    with pytest.raises(SceneError, match=r"labels image 'frame_00009.jpg', which is not among the scene's 2 images "
                                         r"\(frame_00001.jpg, frame_00002.jpg, \.\.\.\)"):
        read_lerf_labels(tmp_path / "label", frames)


def test_langsplat_layout_labels_beside_a_colmap_scene(tmp_path):
    """lerf_ovs/label/<scene>/frame_*.json beside lerf_ovs/<scene>/ (images/, sparse/0): the labelled
    frames are the test views, undistorted like the photos."""
    pytest.importorskip("pycolmap")
    from test_photo_scenes import colmap_text

    from rg_core.io.captures import read_scene

    root = tmp_path / "lerf_ovs" / "teatime"
    frames_of(root, n=9)
    colmap_text(root / "sparse" / "0", [(1, "SIMPLE_RADIAL", 64, 48, [50.0, 32.0, 24.0, -0.2])],
                [(i + 1, np.eye(3), np.array([0.1 * i, 0, 0]), 1, f"frame_{i + 1:05d}.jpg") for i in range(9)])
    (tmp_path / "lerf_ovs" / "label" / "teatime").mkdir(parents=True)
    (tmp_path / "lerf_ovs" / "label" / "teatime" / "frame_00002.json").write_text(json.dumps(LABEL))
    s = read_scene(root)
    assert s.labels.benchmark == "lerf_ovs" and [f.index for f in s.test] == [1] and len(s.train) == 9
    v = s.labels.views[0]
    und = v.frame.undistort
    assert und is not None
    duck = v.masks()["rubber duck"]
    ys, xs = np.nonzero(duck[:, :25])   # the first square, moved by the undistortion
    centre = und.points(np.array([[14.5, 14.5]]))[0]
    assert abs(xs.mean() - centre[0]) < 0.6 and abs(ys.mean() - centre[1]) < 0.6
    b = v.frame_boxes()["rubber duck"][0]
    assert b[0] <= centre[0] <= b[2] and b[1] <= centre[1] <= b[3]


# --------------------------------------------------------------------------- 3D-OVS

def test_3dovs_segmentations_and_argmax_miou(tmp_path):
    frames = frames_of(tmp_path, n=3)
    seg = tmp_path / "segmentations"
    (seg / "02").mkdir(parents=True)
    (seg / "classes.txt").write_text("table\nbanana\n\n")
    left = np.zeros((48, 64), bool)
    left[:, :32] = True
    write_mask(seg / "02" / "banana.png", left)
    write_mask(seg / "02" / "table.png", ~left)
    labels = read_3dovs_segmentations(tmp_path, frames)
    assert labels.benchmark == "3d_ovs" and labels.classes == ["banana", "table"]   # sorted, as 3D-OVS sorts them
    (v,) = labels.views
    assert v.frame is frames[2]
    m = v.masks()
    gt = np.stack([m["banana"], m["table"]])
    x = np.broadcast_to(np.arange(64), (48, 64))
    scores = np.stack([(x < 16).astype(float), (x >= 16).astype(float) * 0.5])   # banana predicted on x < 16 only
    ious, acc = argmax_segmentation(scores, gt)
    np.testing.assert_allclose(ious, [16 / 32, 32 / 48])
    assert acc == pytest.approx(48 / 64)
    ious, _ = argmax_segmentation(np.stack([scores[0], scores[1], np.zeros((48, 64))]), np.stack([*gt, np.zeros((48, 64), bool)]))
    assert ious[2] == 0.0   # a class absent from the view and never predicted: 0, as 3D-OVS's scorer counts it
    (seg / "02" / "table.png").unlink()
    with pytest.raises(SceneError, match=r"segmentations/02: no mask for class\(es\) table"):
        read_3dovs_segmentations(tmp_path, frames)
    write_mask(seg / "02" / "table.png", ~left)
    (seg / "x7").mkdir()
    with pytest.raises(SceneError, match=r"a view folder must be named by the image's position in name order \(0-2\)"):
        read_3dovs_segmentations(tmp_path, frames)


# --------------------------------------------------------------------------- over a grounded map

def label_files(scene, folder, names=None, up=4):
    """LERF-OVS label files for a scene's test views, from its visible masks (a polygon per
    connected part) drawn at `up` times the views' size, as LERF-OVS's labels are drawn on photos
    far larger than a CPU renders; `names` maps object ids to categories (default: their names)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = names or {o.id: o.name for o in scene.objects}
    for f in scene.test:
        vis = cv2.resize(f.load_visible_mask(), None, fx=up, fy=up, interpolation=cv2.INTER_NEAREST)
        objs = []
        for oid, name in names.items():
            cs, _ = cv2.findContours((vis == oid).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            for c in cs:
                if len(c) >= 3 and cv2.contourArea(c) >= 15 * up * up:
                    p = c.reshape(-1, 2)
                    objs.append({"category": name, "group": oid, "segmentation": p.tolist(),
                                 "bbox": [*p.min(0).tolist(), *p.max(0).tolist()], "area": float(cv2.contourArea(c)),
                                 "iscrowd": 0})
        info = {"name": f.image_path.name, "width": up * f.intrinsics.width, "height": up * f.intrinsics.height}
        (folder / f"{f.image_path.stem}.json").write_text(json.dumps({"info": info, "objects": objs}))


def test_both_protocols_over_a_grounded_map(grounder, synth_scene, tmp_path):
    label_files(synth_scene, tmp_path / "label")
    labels = read_lerf_labels(tmp_path / "label", synth_scene.frames)
    s = Scene(synth_scene.root, synth_scene.train, synth_scene.test, labels=labels)
    out = evaluate_labels(grounder, s)["lerf_ovs"]
    assert out["views"] == 2 and out["pairs"] >= 5 and out["categories"] >= 3
    assert set(out["levels_m"]) <= {"part", "object", "group"} and sum(out["2d_relevancy"]["levels_kept"].values()) == out["pairs"]
    assert "LangSplat" in out["2d_relevancy"]["protocol"] and "OpenGaussian" in out["3d_selection"]["protocol"]
    assert out["3d_selection"]["miou"] >= 50, out
    # the 2D rule on this map (random name vectors: object 0.70 against 0.59 around it) finds less:
    # measured 17.7 mIoU, 60 % localized, 3D selection 73.2 (2026-12-02)
    assert out["2d_relevancy"]["miou"] >= 8 and out["2d_relevancy"]["localization"] >= 40, out
    # the same masks under each other's names: both protocols see it
    ids = [o.id for o in synth_scene.objects]
    label_files(synth_scene, tmp_path / "wrong", {a: o.name for a, o in zip(ids, synth_scene.objects[1:] + synth_scene.objects[:1])})
    s.labels = read_lerf_labels(tmp_path / "wrong", synth_scene.frames)
    bad = evaluate_labels(grounder, s)["lerf_ovs"]
    assert bad["3d_selection"]["miou"] < out["3d_selection"]["miou"] - 30, (bad, out)
    assert bad["2d_relevancy"]["miou"] < out["2d_relevancy"]["miou"], (bad, out)


def test_rg_eval_prints_the_benchmark_figures(synth_scene_dir, minilm_map_file, tmp_path):
    root = tmp_path / "scene"
    shutil.copytree(synth_scene_dir, root)
    from rg_core.io.scene import read_reasoninggd

    label_files(read_reasoninggd(root), root / "label")
    obj = json.loads((root / "objects.json").read_text())["objects"][0]
    (tmp_path / "q.json").write_text(json.dumps([{"object_id": obj["id"], "explicit": obj["name"], "implicit": []}]))
    r = subprocess.run([sys.executable, "-m", "rg_core.cli", "eval", str(root), "--map", str(minilm_map_file),
                        "--queries", str(tmp_path / "q.json"), "--json", "--quiet"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    ev = json.loads(r.stdout)["eval"]
    assert ev["explicit"]["pairs"] >= 1   # the scene's queries are still scored
    lo = ev["lerf_ovs"]
    assert lo["pairs"] >= 5 and 0 <= lo["2d_relevancy"]["miou"] <= 100 and 0 <= lo["2d_relevancy"]["localization"] <= 100
    assert lo["3d_selection"]["miou"] >= 50, lo


def test_3d_ovs_over_a_grounded_map(grounder, synth_scene, tmp_path):
    """3D-OVS segmentations of the test views (one class an object, masks at 4x the views' size):
    the argmax mIoU and the 3D selection, and both fall when the classes swap names."""
    def write(root, names):
        seg = root / "segmentations"
        seg.mkdir(parents=True)
        (seg / "classes.txt").write_text("\n".join(names.values()) + "\n")
        for f in synth_scene.test:
            vis = cv2.resize(f.load_visible_mask(), None, fx=4, fy=4, interpolation=cv2.INTER_NEAREST)
            for oid, name in names.items():
                write_mask(seg / f"{f.index:02d}" / f"{name}.png", vis == oid)
        return read_3dovs_segmentations(root, synth_scene.frames)

    objs = synth_scene.objects
    s = Scene(synth_scene.root, synth_scene.train, synth_scene.test, labels=write(tmp_path / "a", {o.id: o.name for o in objs}))
    assert [v.frame for v in s.labels.views] == synth_scene.test
    out = evaluate_labels(grounder, s)["3d_ovs"]
    assert out["views"] == 2 and out["classes"] == sorted(o.name for o in objs)
    assert "3D-OVS" in out["2d_relevancy"]["protocol"] and "OpenGaussian" in out["3d_selection"]["protocol"]
    s.labels = write(tmp_path / "b", {o.id: n.name for o, n in zip(objs, objs[1:] + objs[:1])})
    bad = evaluate_labels(grounder, s)["3d_ovs"]
    assert out["3d_selection"]["miou"] >= 50 and bad["3d_selection"]["miou"] < out["3d_selection"]["miou"] - 30, (out, bad)
    assert out["2d_relevancy"]["miou"] > bad["2d_relevancy"]["miou"], (out, bad)


def test_rg_eval_on_photos_without_depth_scores_a_map_built_elsewhere(synth_scene, minilm_map_file, tmp_path):
    """The session scene as COLMAP photos (no depth, no objects, no queries) with LERF-OVS labels:
    `rg eval --map` scores the RGB-D map of the same views with the benchmark's figures only."""
    pytest.importorskip("pycolmap")
    from test_photo_scenes import scene_as_colmap

    root = scene_as_colmap(synth_scene, tmp_path / "photos")
    label_files(synth_scene, root / "label")
    r = subprocess.run([sys.executable, "-m", "rg_core.cli", "eval", str(root), "--map", str(minilm_map_file), "--json",
                        "--quiet"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    ev = json.loads(r.stdout)["eval"]
    assert set(ev) == {"lerf_ovs"} and ev["lerf_ovs"]["views"] == 2, ev
    assert ev["lerf_ovs"]["3d_selection"]["miou"] >= 50, ev
