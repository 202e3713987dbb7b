"""examples/*.py run as a user runs them (python examples/X.py ...), on the session's small scene."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run(name: str, *args: str) -> str:
    r = subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"{name}: {r.stderr[-3000:]}"
    return r.stdout


def test_every_example_is_run_here():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == ["amodal_mask.py", "ground_query.py", "map_scene.py"]


def test_map_ground_and_mask(synth_scene_dir, tmp_path):
    from rg_core.io.scene import read_reasoninggd

    name = read_reasoninggd(synth_scene_dir).objects[0].name
    out = run("map_scene.py", str(synth_scene_dir), str(tmp_path / "s.rgmap"), "--supervision", "oracle",
              "--field-seconds", "5", "--width", "160")
    assert "keyframes" in out and (tmp_path / "s.rgmap").is_file()
    out = run("ground_query.py", str(tmp_path / "s.rgmap"), name)
    assert "success: True" in out and "Gaussians, centre" in out, out
    out = run("amodal_mask.py", str(tmp_path / "s.rgmap"), name, str(tmp_path / "masks"))
    amodal = cv2.imread(str(tmp_path / "masks" / "amodal.png"), cv2.IMREAD_GRAYSCALE)
    visible = cv2.imread(str(tmp_path / "masks" / "visible.png"), cv2.IMREAD_GRAYSCALE)
    assert amodal is not None and visible is not None and (amodal > 0).sum() >= (visible > 0).sum() > 0, out
