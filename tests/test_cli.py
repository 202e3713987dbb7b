"""The `rg` command: exactly one JSON object on stdout with --json, errors as JSON too."""
import json
import subprocess
import sys

import numpy as np


def run_rg(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "rg_core.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_synth_json(tmp_path):
    r = run_rg("synth", str(tmp_path / "s"), "--views", "3", "--size", "64x48", "--objects", "2",
               "--seed", "5", "--workers", "1", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)  # the whole of stdout is one JSON object (pybullet's prints go to stderr)
    assert out["views"] == 3 and out["size"] == [64, 48] and len(out["objects"]) == 2
    assert (tmp_path / "s" / "images" / "0002.png").is_file()


def test_synth_missing_objects_dir_is_a_clear_error(tmp_path):
    r = run_rg("synth", str(tmp_path / "s"), "--objects-dir", str(tmp_path / "missing"), "--json")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "--objects-dir does not exist" in json.loads(r.stdout)["error"]


def test_demo_writes_contact_sheet(tmp_path):
    import cv2

    # Small budgets: the test checks that the whole main job runs and reports, not its accuracy.
    cfg = tmp_path / "demo.yaml"
    cfg.write_text("demo:\n  views: 16\n  width: 160\n  height: 120\n  field_seconds: 3.0\n  supervision: oracle\n"
                   "map:\n  iters_per_keyframe: 3\n  final_iters: 0\n")
    r = run_rg("--config", str(cfg), "demo", "--out", str(tmp_path / "demo"), "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    img = cv2.imread(out["contact_sheet"])
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 600
    assert np.std(img) > 10  # a picture, not a blank page
    assert set(out["answers"]) == {"explicit", "implicit"}
    for a in out["answers"].values():
        assert a["query"] and isinstance(a["success"], bool) and a["message"]
        if a["success"]:
            assert a["objects"] and cv2.imread(a["pictures"]["figure"]) is not None
            # the visible mask follows the view's depth and colour images (synthetic views have both), as the node's does
            m = a["masks"]
            assert m["visible_follows_depth"] is True and m["visible_follows_image"] is True, m
            assert (m["width"], m["height"]) == (160, 120), m
            assert m["visible_pixels"] == int((cv2.imread(a["pictures"]["visible"], cv2.IMREAD_GRAYSCALE) > 0).sum())
    assert any(a["success"] for a in out["answers"].values()), out["answers"]
    assert (tmp_path / "demo" / "scene.rgmap").is_file()
    # rg graph on the demo's map: its objects with names, confidences, centres and colours
    r = run_rg("graph", str(tmp_path / "demo" / "scene.rgmap"), "--json")
    assert r.returncode == 0, r.stderr
    graph = json.loads(r.stdout)
    objs = graph["objects"]
    assert objs and all(o["names"] and len(o["centre"]) == 3 and o["colour"] for o in objs), objs
    assert len(graph["up"]) == 3 and all(r["predicate"] in ("on", "near") for r in graph["relations"])
    r = run_rg("graph", str(tmp_path / "demo" / "scene.rgmap"))
    assert r.returncode == 0 and all(o["name"] in r.stdout for o in objs) and "centre (" in r.stdout, r.stdout
    # The human summary (what `rg demo` prints without --json) names what a person needs.
    from rg_core.viz.summary import demo_summary

    text = demo_summary(out)
    for a in out["answers"].values():
        assert repr(a["query"]) in text and (a["target"] or "-") in text
        if a["success"]:
            assert a["pictures"]["figure"] in text and "centre (" in text and " m, size " in text
    assert out["map"] in text


def test_errors_are_reported(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("synth:\n  view: 3\n")
    r = run_rg("--config", str(cfg), "synth", str(tmp_path / "s"), "--json")
    assert r.returncode == 2
    assert "synth.view: unknown key" in json.loads(r.stdout)["error"]
    r = run_rg("synth", str(tmp_path / "s"), "--size", "64by48")
    assert r.returncode == 2 and "size must look like 320x240" in r.stderr


def test_map_json_reports_everything(synth_scene_dir, tmp_path):
    r = run_rg("map", str(synth_scene_dir), "--out", str(tmp_path / "m.rgmap"), "--width", "80",
               "--iters-per-keyframe", "2", "--max-gaussians", "5000", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["frames"] == 14 and 1 <= out["keyframes"] <= 14 and 0 < out["gaussians"] <= 5000
    assert set(out["seconds"]) >= {"prepare", "check", "seed", "optimise", "prune"} and out["seconds_total"] > 0
    assert out["peak_rss_mb"] > 0 and out["test"]["views"] == 2
    for k in ("psnr", "depth_abs_error_median_m", "coverage"):
        assert k in out["test"]
    assert (tmp_path / "m.rgmap").is_file()
    r = run_rg("map", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.rgmap"), "--json")
    assert r.returncode == 2 and "nowhere: not a scene folder" in json.loads(r.stdout)["error"]
