"""field.steps / `rg eval --field-steps N`: the feature field trains exactly N steps, whatever the
seconds budget and the CPU load (runs compared by count, not by time)."""
import json
import subprocess
import sys

import torch

from rg_core.config import FieldConfig, MapConfig
from rg_core.field import FeatureField
from rg_core.field.oracle import RandomNameEmbedding, oracle_supervision
from rg_core.map.mapper import Mapper
from rg_core.map.run import stream_frames


def run_rg(*args):
    return subprocess.run([sys.executable, "-m", "rg_core.cli", *args], capture_output=True, text=True, timeout=300)


def test_train_without_a_budget_runs_cfg_steps(synth_scene):
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        mapper = Mapper(MapConfig(width=80, iters_per_keyframe=2, final_iters=0, seed_stride=4))
        stream_frames(mapper, synth_scene.train[:4], progress=False)
        oracle_supervision(mapper, synth_scene.train, synth_scene.objects, RandomNameEmbedding(dim=96, seed=0))
        # seconds=0 would train nothing: steps > 0 replaces it
        f = FeatureField(mapper, FieldConfig(rays_per_step=64, steps=5, seconds=0.0))
        assert f.train()["steps"] == 5 and f.steps == 5
        assert f.train(iters=2)["steps"] == 2 and f.steps == 7  # an explicit budget still wins
    finally:
        torch.set_num_threads(n)


def test_rg_eval_field_steps_exact(synth_scene_dir, tmp_path):
    m = tmp_path / "m.rgmap"
    r = run_rg("map", str(synth_scene_dir), "--out", str(m), "--width", "80", "--iters-per-keyframe", "1",
               "--max-gaussians", "2000", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    cfg = tmp_path / "c.yaml"
    cfg.write_text("field:\n  steps: 4\n  seconds: 0.0\n  rays_per_step: 64\n")  # seconds alone: no training
    # The config's field.steps, then the flag over it; the report names the budget it ran.
    for extra, want in (((), 4), (("--field-steps", "7"), 7)):
        r = run_rg("--config", str(cfg), "eval", str(synth_scene_dir), "--map", str(m), "--supervision", "oracle",
                   "--implicit", "0", *extra, "--json", "--quiet")
        assert r.returncode == 0, r.stderr
        field = json.loads(r.stdout)["field"]
        assert field["steps"] == want and field["budget"] == {"steps": want}, field
    # The seconds ceiling, not the stop test, ends training (min steps out of reach): the report says
    # so, since such answers depend on the CPU's load; a fixed count carries no warning.
    cfg.write_text("field:\n  seconds: 0.5\n  converge_min_steps: 100000\n  rays_per_step: 64\n")
    r = run_rg("--config", str(cfg), "eval", str(synth_scene_dir), "--map", str(m), "--supervision", "oracle",
               "--implicit", "0", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    field = json.loads(r.stdout)["field"]
    assert field["stop"]["stopped"] == "seconds" and "0.5 s ceiling" in field["warning"], field
    assert "--field-steps" in field["warning"] and "0.5 s ceiling" in r.stderr
    r = run_rg("--config", str(cfg), "eval", str(synth_scene_dir), "--map", str(m), "--supervision", "oracle",
               "--implicit", "0", "--field-steps", "3", "--json", "--quiet")
    assert r.returncode == 0 and "warning" not in json.loads(r.stdout)["field"], r.stderr
    r = run_rg("eval", str(synth_scene_dir), "--field-steps", "3", "--field-seconds", "1")
    assert r.returncode == 2 and "not allowed with argument" in r.stderr
