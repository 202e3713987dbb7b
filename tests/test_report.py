"""`rg report --tiny` end to end on a tiny scene (seconds), so the command keeps working; and a
section that fails is recorded in the report instead of stopping it."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from rg_core.report.markdown import TITLES


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from rg_core.config import SynthConfig
    from rg_core.synth.generator import default_objects_dir, generate_scene

    out = tmp_path_factory.mktemp("report") / "scene"
    generate_scene(out, SynthConfig(views=8, width=160, height=120, objects=3, seed=5, workers=1),
                   default_objects_dir(), progress=False)
    return out


def _numbers(table):
    return [v for row in table["rows"] for v in row if isinstance(v, (int, float)) and not isinstance(v, bool)]


def test_tiny_report_end_to_end(tiny_scene, tmp_path, capfd):
    from PIL import Image

    from rg_core.cli import main

    out = tmp_path / "rep"
    assert main(["report", str(tiny_scene), "--out", str(out), "--tiny", "--json", "--quiet"]) == 0
    summary = json.loads(capfd.readouterr().out.strip().splitlines()[-1])
    assert summary["failed_sections"] == [], summary
    md = (out / "report.md").read_text()
    assert "## Recommended settings" in md and "Answer within 1 s" in md and "Answer within 10 s" in md
    for title in TITLES.values():
        assert f"## {title}" in md, title
    rep = json.loads((out / "report.json").read_text())
    plots = [p for s in rep["sections"].values() for p in s.get("plots", [])]
    assert len(plots) >= 5
    for p in plots:
        with Image.open(p) as im:
            im.verify()
            assert im.format == "PNG" and im.size[0] > 100
        assert f"]({p.split(str(out) + '/')[-1]})" in md
    for name, sec in rep["sections"].items():
        assert sec["tables"], name
        for t in sec["tables"]:
            nums = _numbers(t)
            assert nums, (name, t["title"])
            assert all(math.isfinite(v) for v in nums), (name, t["title"], t["rows"])
    sav = rep["sections"]["savings"]["data"]
    names = [r["saving"] for r in sav["mapping"] + sav["grounding"]]
    assert any(n.startswith("coarse-to-fine") for n in names) and any("default supervision" in n for n in names), names
    assert rep["sections"]["stability"]["data"]["counts"]["passed"] >= 1
    assert rep["sections"]["stability"]["data"]["counts"]["failed"] == 0
    lat = rep["sections"]["latency"]["data"]["rows"]
    assert any(r["default_map"] for r in lat) and all(r["median_s"] > 0 for r in lat)


def test_failing_section_is_recorded_and_the_rest_runs(tiny_scene, tmp_path):
    from rg_core.report import tiny_budgets
    from rg_core.report.runner import run_report

    rep = run_report(tiny_scene, tmp_path / "rep", tiny_budgets(frames=(0,)), sections=("mapping", "memory"),
                     progress=False)
    assert "error" in rep["sections"]["memory"] and "frame counts" in rep["sections"]["memory"]["error"]
    assert "error" not in rep["sections"]["mapping"]
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "## Peak memory against frames" in md and "**This section failed**" in md
    assert "## Mapping: error against run time" in md and "![" in md
    assert not (tmp_path / "rep" / "plots" / "photo_heldout_psnr_vs_time.png").exists()   # an RGB-D scene: no fit curve


def test_a_scene_without_depth_reports_the_fits_psnr_against_time(tiny_scene, tmp_path):
    """The tiny scene's photos alone (depth images and depth_file_path removed, 1,000 sparse points):
    the mapping section fits them and plots held-out PSNR against seconds from the fit's summary."""
    import shutil

    from PIL import Image

    from conftest import photos_only
    from rg_core.report import tiny_budgets
    from rg_core.report.runner import run_report

    photos = photos_only(Path(shutil.copytree(tiny_scene, tmp_path / "photos")), points=1000)
    rep = run_report(photos, tmp_path / "rep", tiny_budgets(), sections=("mapping",), progress=False)
    sec = rep["sections"]["mapping"]
    assert "error" not in sec, sec
    png = tmp_path / "rep" / "plots" / "photo_heldout_psnr_vs_time.png"
    assert sec["plots"] == [str(png)]
    with Image.open(png) as im:
        im.verify()
        assert im.format == "PNG" and im.size[0] > 100
    assert "](plots/photo_heldout_psnr_vs_time.png)" in (tmp_path / "rep" / "report.md").read_text()
    curve = sec["photo"]["heldout_psnr"]
    # every check_every steps until the stop is decided at (1 - join_share) x 60 = 51, then the held-out views join
    assert [r[0] for r in curve] == [15, 30, 45, 51] and all(math.isfinite(r[2]) for r in curve)
    assert sec["photo"]["decided"] == 51 and sec["photo"]["steps"] == 60 and sec["photo"]["heldout_views"]
    assert sec["tables"][1]["rows"] == curve and curve[-1][1] >= curve[0][1]


def test_unknown_section_and_degraded_frames(tiny_scene, tmp_path):
    import numpy as np

    from rg_core.io.captures import read_scene
    from rg_core.report import tiny_budgets
    from rg_core.report.inputs import degrade
    from rg_core.report.runner import run_report

    with pytest.raises(ValueError, match="unknown sections"):
        run_report(tiny_scene, tmp_path, tiny_budgets(), sections=("mappin",))
    f = read_scene(tiny_scene).train[1]
    clean = f.load_depth()
    holes = degrade([f], "missing_depth_20")[0].load_depth()
    lost = ((clean > 0) & (holes == 0)).sum() / max((clean > 0).sum(), 1)
    assert 0.15 < lost < 0.25
    noisy = degrade([f], "depth_noise_1cm")[0].load_depth()
    both = (clean > 0) & (noisy > 0)
    assert 0.007 < np.std(noisy[both] - clean[both]) < 0.013
    moved = degrade([f], "pose_noise_1cm_1deg")[0].cam_to_world
    assert abs(np.linalg.norm(moved[:3, 3] - f.cam_to_world[:3, 3]) - 0.01) < 1e-6
    assert np.array_equal(degrade([f], "depth_noise_5cm")[0].load_depth(), degrade([f], "depth_noise_5cm")[0].load_depth())
