"""Many scenes in this process (issue 64): `rg synth OUT --seeds A-B` and `rg eval SCENE [SCENE ...]`
(paths, a folder of scenes, a list file) with --results: per-scene records, failures recorded while the
others go on, reruns that skip and --retry-failed, the aggregate (JSON, table, PNG) and per-scene
figures equal to a single-scene `rg eval`. Ray's engine: tests/test_many_scenes_ray.py."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

# The smallest scenes and budgets that still ask every kind of query: 8 views of 64x48 (one test
# view), 3 objects, oracle supervision, 5 field steps (a fixed count: the figures do not depend on time).
SYNTH = ["--views", "8", "--size", "64x48", "--objects", "3"]
EVAL = ["--supervision", "oracle", "--field-steps", "5", "--implicit", "1", "--relational", "2",
        "--map.width", "64", "--map.iters_per_keyframe", "1", "--map.final_iters", "0", "--field.rays_per_step", "64"]


def run_rg(*args, **kw):
    return subprocess.run([sys.executable, "-m", "rg_core.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, **kw)


def canonical(figs) -> str:
    """Figures as sorted JSON: NaN (AUROC of a scene whose answers are all right) equals NaN."""
    return json.dumps(figs, sort_keys=True)


def scene_figures(agg: dict) -> dict:
    """scene -> its figures without the seconds (what must not depend on where or when it ran)."""
    return {s["scene"]: canonical({k: v for k, v in (s["eval"] or {}).items() if k != "seconds"})
            for s in agg["scenes"]}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("many") / "scenes"
    r = run_rg("synth", out, "--seeds", "1-2", *SYNTH, "--workers", "1", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["engine"]["name"] == "local" and s["scenes"] == {"ok": 2, "failed": 0, "skipped_ok": 0,
                                                              "skipped_failed": 0}, s
    return out


def test_synth_seeds_make_the_single_command_s_scenes_and_resume(scenes, tmp_path):
    assert sorted(p.name for p in scenes.iterdir() if p.is_dir() and not p.name.startswith(".")) == \
        ["scene_00001", "scene_00002"]
    r = run_rg("synth", tmp_path / "one", "--seed", "2", *SYNTH, "--workers", "1", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    for f in ("images/0003.png", "depth/0003.png", "queries.json", "objects.json", "transforms_train.json"):
        assert (scenes / "scene_00002" / f).read_bytes() == (tmp_path / "one" / f).read_bytes(), f
    r = run_rg("synth", scenes, "--seeds", "1-2", *SYNTH, "--json", "--quiet")   # done: nothing to run
    assert r.returncode == 0 and json.loads(r.stdout)["scenes"]["skipped_ok"] == 2, r.stderr
    r = run_rg("synth", scenes, "--seeds", "1-2", *SYNTH[:-1], "4", "--json", "--quiet")
    assert r.returncode == 2 and "made with other settings (synth differ)" in json.loads(r.stdout)["error"]
    r = run_rg("synth", tmp_path / "x", "--seeds", "5-3", "--json")
    assert r.returncode == 2 and "--seeds wants A-B" in r.stderr
    r = run_rg("synth", tmp_path / "x", "--ray", "--json")
    assert r.returncode == 2 and "give --seeds A-B" in json.loads(r.stdout)["error"]


def test_eval_many_records_failures_resumes_and_aggregates(scenes, tmp_path):
    bad = tmp_path / "not_a_scene"
    bad.mkdir()
    res = tmp_path / "res"
    r = run_rg("eval", scenes, bad, "--results", res, *EVAL, "--json")
    assert r.returncode == 0, r.stderr
    agg = json.loads(r.stdout)
    assert agg == json.loads((res / "aggregate.json").read_text())
    assert agg["engine"]["name"] == "local" and agg["engine"]["version"].startswith("python ")
    by = {s["scene"]: s for s in agg["scenes"]}
    assert list(by) == ["scene_00001", "scene_00002", "not_a_scene"]
    assert by["not_a_scene"]["status"] == "failed" and "not a scene folder" in by["not_a_scene"]["error"]
    assert by["not_a_scene"]["eval"] is None
    for name in ("scene_00001", "scene_00002"):
        s = by[name]
        assert s["status"] == "ok" and s["error"] is None, s
        assert set(s["eval"]) >= {"explicit", "implicit", "relational", "all", "seconds"}, s["eval"]
        for k in ("explicit", "implicit", "relational", "all"):
            assert set(s["eval"][k]) == {"pairs", "miou", "localization", "answers", "auroc", "ece"}
        rec = json.loads((res / "scenes" / f"{name}.json").read_text())   # the whole report is kept per scene
        assert rec["status"] == "ok" and rec["result"]["eval"]["explicit"]["pairs"] == s["eval"]["explicit"]["pairs"]
    a = agg["aggregate"]
    assert a["scenes"] == {"ok": 2, "failed": 1}
    # pooled: pairs add up; mIoU is the pair-weighted mean of the scenes'; AUROC/ECE over all answers
    for k in ("explicit", "implicit", "relational", "all"):
        assert a[k]["pairs"] == sum(by[n]["eval"][k]["pairs"] for n in ("scene_00001", "scene_00002"))
        assert a[k]["answers"] == sum(by[n]["eval"][k]["answers"] for n in ("scene_00001", "scene_00002"))
        w = sum(by[n]["eval"][k]["miou"] * by[n]["eval"][k]["pairs"] for n in ("scene_00001", "scene_00002"))
        assert a[k]["miou"] == pytest.approx(w / a[k]["pairs"], abs=0.01)
    assert a["all"]["pairs"] == sum(a[k]["pairs"] for k in ("explicit", "implicit", "relational"))
    assert Path(agg["plot"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a rerun skips what is recorded; --retry-failed runs the failed one again (and it fails again)
    r = run_rg("eval", scenes, bad, "--results", res, *EVAL, "--json", "--quiet")
    run = json.loads(r.stdout)["run"]
    assert r.returncode == 0 and run["driver_peak_rss_mb"] > 0, r.stderr
    assert {k: run[k] for k in ("tasks", "skipped_ok", "skipped_failed", "workers", "address")} == \
        {"tasks": 0, "skipped_ok": 2, "skipped_failed": 1, "workers": None, "address": None}
    r = run_rg("eval", scenes, bad, "--results", res, *EVAL, "--retry-failed", "--json", "--quiet")
    assert r.returncode == 0 and json.loads(r.stdout)["run"]["tasks"] == 1, r.stderr
    # other settings into the same folder: refused, naming what differs
    r = run_rg("eval", scenes, "--results", res, *EVAL[:3], "6", *EVAL[4:], "--json", "--quiet")
    assert r.returncode == 2 and "made with other settings" in json.loads(r.stdout)["error"], r.stdout
    # the table on stdout: a line per scene, the error of the failed one, the pooled lines
    r = run_rg("eval", scenes, bad, "--results", res, *EVAL, "--quiet")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith("scene") and "AUROC" in lines[0]
    assert any(ln.startswith("not_a_scene") and "not a scene folder" in ln for ln in lines)
    assert any(ln.startswith("scene_00001") and " ok " in ln for ln in lines)
    assert "pooled over 2 scenes (1 failed):" in r.stdout and any(ln.startswith("relational") for ln in lines)


def test_many_scene_figures_equal_single_scene_runs_and_list_files(scenes, tmp_path):
    """Each scene's figures do not depend on what ran before it in the process (the list puts
    scene 2 first), and equal `rg eval SCENE` on it alone, whose output keeps its old shape."""
    lst = tmp_path / "list.txt"
    lst.write_text(f"# two scenes\n{scenes / 'scene_00002'}\n\n{Path('..') / scenes.name / 'scene_00001'}\n")
    (tmp_path / scenes.name).symlink_to(scenes)
    lst2 = tmp_path / "sub" / "list.txt"
    lst2.parent.mkdir()
    lst2.write_text(lst.read_text())
    r = run_rg("eval", lst2, "--results", tmp_path / "res", *EVAL, "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    agg = json.loads(r.stdout)
    assert [s["scene"] for s in agg["scenes"]] == ["scene_00002", "scene_00001"]
    many = scene_figures(agg)
    for name in ("scene_00001", "scene_00002"):
        r = run_rg("eval", scenes / name, *EVAL, "--json", "--quiet")
        assert r.returncode == 0, r.stderr
        one = json.loads(r.stdout)
        assert "engine" not in one and {"eval", "field", "seconds_build", "supervision_kind"} <= set(one)
        from rg_core.eval.many import figures

        assert canonical({k: v for k, v in figures(one, None).items() if k != "seconds"}) == many[name]
    r = run_rg("eval", tmp_path / "missing.txt", "--json")
    assert r.returncode == 2 and "scene list file does not exist" in json.loads(r.stdout)["error"]
    r = run_rg("eval", scenes, "--map", "m.rgmap", "--json")
    assert r.returncode == 2 and "--map scores one scene's map" in json.loads(r.stdout)["error"]
    r = run_rg("eval", scenes, "--workers", "2", "--json")
    assert r.returncode == 2 and "--workers needs --ray" in json.loads(r.stdout)["error"]


def test_ray_flag_without_ray_says_how_to_install(scenes):
    """A Python without Ray (its import fails, as where the extra is not installed)."""
    code = ("import sys; sys.modules['ray'] = None; from rg_core.cli import main; "
            f"sys.exit(main(['eval', {str(scenes)!r}, '--ray', '--json', '--quiet']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    err = json.loads(r.stdout)["error"]
    assert "--ray needs Ray, which is not installed" in err and "pip install .[ray]" in err
