"""docs/benchmarks.md is generated from benchmarks/results/*.json (benchmarks/make_docs.py): the
committed page must equal a fresh regeneration, every result must fit the shared schema of
benchmarks/_common.py, and every benchmark script must have its result file, so the page can
neither drift from the JSON nor silently lose a script."""
from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import _common  # noqa: E402
import make_docs  # noqa: E402

RESULTS = sorted((ROOT / "benchmarks" / "results").glob("*.json"))


def test_committed_page_equals_regeneration(tmp_path):
    out = tmp_path / "benchmarks.md"
    assert make_docs.main(["--out", str(out)]) == 0
    assert out.read_text(encoding="utf-8") == (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8"), \
        "docs/benchmarks.md differs from benchmarks/results: run python benchmarks/make_docs.py"


def test_check_flag_fails_on_a_stale_page(tmp_path):
    out = tmp_path / "benchmarks.md"
    out.write_text((ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8") + "hand edit\n")
    assert make_docs.main(["--out", str(out), "--check"]) == 1


@pytest.mark.parametrize("path", RESULTS, ids=[p.stem for p in RESULTS])
def test_result_fits_the_schema(path):
    rec = json.loads(path.read_text(encoding="utf-8"))
    assert _common.check_result(rec) == []
    assert rec["script"] == path.stem
    for plot in rec.get("plots", []):
        assert (ROOT / plot).is_file(), f"{path.name}: plot {plot} is not in the repository"


def test_every_script_has_a_result():
    scripts = {p.stem for p in (ROOT / "benchmarks").glob("bench_*.py")}
    assert scripts and scripts <= {p.stem for p in RESULTS}


def test_schema_check_rejects_bad_records():
    good = json.loads(RESULTS[0].read_text(encoding="utf-8"))
    bad_cases = [("date", "25/11/2026"), ("notes", "two\nlines"), ("rows", []), ("machine", {"cpu": "x"}),
                 ("source", "from memory")]
    for key, value in bad_cases:
        rec = copy.deepcopy(good)
        rec[key] = value
        assert _common.check_result(rec), f"{key}={value!r} passed the check"
    rec = copy.deepcopy(good)
    rec["rows"][0]["long_cell"] = "x" * (_common.MAX_CELL + 1)
    assert _common.check_result(rec)
    rec["rows"][0] = {"Not Snake": 1}
    assert _common.check_result(rec)


def test_write_result_round_trip(tmp_path):
    import rg_core.render  # noqa: F401  (as a script that renders)

    png = tmp_path / "p.png"
    png.write_bytes(b"\x89PNG")
    path = _common.write_result("bench_demo", [{"case": "a", "time_s": 1.25}], "one line", command="python x.py",
                                plots=[png, tmp_path / "missing.png"], out_dir=tmp_path / "res")
    rec = json.loads(path.read_text())
    assert _common.check_result(rec) == [] and rec["command"] == "python x.py"
    assert rec["machine"]["cores"] >= 1 and len(rec["plots"]) == 1
    assert ("PURE-TORCH" in rec["notes"]) != _common.rasterizer_built()


def test_results_say_when_the_pure_torch_rasterizer_rendered(tmp_path, monkeypatch):
    from rg_core.render import fast_cpu

    monkeypatch.setattr(fast_cpu, "_lib", None)
    rec = json.loads(_common.write_result("bench_demo", [{"case": "a"}], "x", command="python x.py",
                                          out_dir=tmp_path).read_text())
    assert rec["notes"].endswith("PURE-TORCH RASTERIZER (the C++ kernel was not built)") and not _common.check_result(rec)
    assert make_docs.header("explicit_visible_miou") == "explicit visible mIoU" and make_docs.cell(0.123456) == "0.1235" and make_docs.cell(47.0) == "47.0"


def test_recorded_commands_run_anywhere(tmp_path):
    """A recorded command names no path of the machine that ran it: paths in the checkout become
    relative, others bench_out/<name>, and a baseline checkout comes with the commands that make it."""
    argv = ["/x/benchmarks/bench_demo.py", "--out", "/work/tmp/run3", "--scene", str(ROOT / "examples"),
            "--baseline-code", str(ROOT), "--json"]
    cmd = _common.command_line(argv)
    commit = _common.commit_of(ROOT).removesuffix("-dirty")
    assert cmd == (f"git worktree add ../baseline {commit} && (cd ../baseline && python setup.py -q build_ext "
                   "--inplace) && python benchmarks/bench_demo.py --out bench_out/run3 --scene examples "
                   "--baseline-code ../baseline"), cmd
    rec = json.loads(RESULTS[0].read_text(encoding="utf-8"))
    rec["command"] = "python benchmarks/bench_x.py --out /work/tmp/x"
    assert any("absolute path" in b for b in _common.check_result(rec))
