"""Regenerate docs/benchmarks.md from the recorded results, so the page never drifts from the JSON.

    python benchmarks/make_docs.py [--out docs/benchmarks.md] [--check]

Reads benchmarks/docs_intro.md (title and the "In short" summary, written by hand) and every
benchmarks/results/*.json (the shared schema of benchmarks/_common.py; a script writes its own with
--record), and writes one section per result: its command, date, machine, origin, one table of
short cells (units in the column headers) and links to its plots. --check writes nothing and exits 1
when the page differs from what the results give (tests/test_bench_docs.py does the same).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, ROOT, check_result  # noqa: E402

DOC = ROOT / "docs" / "benchmarks.md"
INTRO = ROOT / "benchmarks" / "docs_intro.md"
# reading order: the pipeline's stages, then end-to-end figures; any other result file follows, by name
ORDER = ("bench_rasterize", "bench_synth", "bench_mapping", "bench_photo", "bench_bag", "bench_field", "bench_perception",
         "bench_bop_naming", "bench_reasoning", "bench_latency", "bench_cache_accuracy", "bench_eval",
         "bench_confidence", "bench_relations", "bench_llm_parse", "bench_first_answer", "bench_room", "bench_teach", "bench_endurance", "bench_busy_map", "bench_report")
UNITS = {"s": "s", "ms": "ms", "db": "dB", "mm": "mm", "pct": "%", "mb": "MB", "gb": "GB"}
WORDS = {"miou": "mIoU", "iou": "IoU", "psnr": "PSNR", "rss": "RSS", "ycb": "YCB", "top1": "top-1", "top3": "top-3",
         "scene7": "7-name", "tf": "TF"}


def header(key: str) -> str:
    """Column title of a row key: 'fwd_bwd_ms' -> 'fwd bwd (ms)', 'psnr_db' -> 'psnr (dB)'."""
    stem, _, unit = key.rpartition("_")
    words = lambda k: " ".join(WORDS.get(w, w) for w in k.split("_"))
    return f"{words(stem)} ({UNITS[unit]})" if stem and unit in UNITS else words(key)


def cell(v) -> str:
    """A short cell: numbers as recorded when short, else to 4 significant digits."""
    if isinstance(v, float) and len(repr(v)) > 7:
        return f"{v:.4g}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def table(rows: list[dict]) -> list[str]:
    """Markdown table over the union of the rows' keys, in first-seen order; missing cells blank."""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(header(k) for k in keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(cell(r[k]) if k in r else "" for k in keys) + " |" for r in rows]
    return lines


def section(rec: dict) -> list[str]:
    m = rec["machine"]
    origin = f"; {rec['source']}" if "source" in rec else "; measured with `--record`"
    lines = [f"## {rec['script']}", "",
             f"`{rec['command']}`  ",
             f"{rec['date']}, {m['cpu']}, {m['cores']} cores, Python {m['python']}, torch {m['torch']}{origin}.  ",
             rec["notes"], ""]
    lines += table(rec["rows"])
    if rec.get("plots"):
        # relative to docs/, where the page lives (wherever --out writes a copy)
        links = ", ".join(f"[{Path(p).name}]({Path(os.path.relpath(ROOT / p, DOC.parent)).as_posix()})"
                          for p in rec["plots"])
        lines += ["", f"Plots: {links}"]
    return lines + [""]


def load_results(results: Path = RESULTS) -> list[dict]:
    """Every result record, in ORDER then by name; a record that breaks the schema stops the build."""
    files = sorted(results.glob("*.json"), key=lambda p: (ORDER.index(p.stem) if p.stem in ORDER else len(ORDER), p.stem))
    recs = []
    for p in files:
        rec = json.loads(p.read_text(encoding="utf-8"))
        bad = check_result(rec)
        if bad:
            raise ValueError(f"{p}: {bad}")
        if rec["script"] != p.stem:
            raise ValueError(f"{p}: script {rec['script']!r} is not the file's name")
        recs.append(rec)
    return recs


def render(results: Path = RESULTS, intro: Path = INTRO) -> str:
    """The whole page as text."""
    recs = load_results(results)
    lines = [intro.read_text(encoding="utf-8").rstrip("\n"), ""]
    lines += ["| result | date | origin |", "|---|---|---|"]
    lines += [f"| [{r['script']}](#{r['script']}) | {r['date']} | {'transcribed' if 'source' in r else 'measured'} |"
              for r in recs]
    lines.append("")
    for r in recs:
        lines += section(r)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(DOC))
    ap.add_argument("--check", action="store_true", help="exit 1 if --out differs from the results; write nothing")
    a = ap.parse_args(argv)
    out = Path(a.out)
    text = render()
    if a.check:
        same = out.is_file() and out.read_text(encoding="utf-8") == text
        print(f"{out}: {'up to date' if same else 'differs from benchmarks/results: run python benchmarks/make_docs.py'}")
        return 0 if same else 1
    out.write_text(text, encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
