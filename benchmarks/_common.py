"""What every benchmark script shares: one small result schema, its writer and checker, machine info,
the `--json` / `--record` ending, and saving a matplotlib figure.

Why one place: docs/benchmarks.md is generated from benchmarks/results/<script>.json
(benchmarks/make_docs.py), so every script must write the same shape:

    {"script": "bench_x", "command": "python benchmarks/bench_x.py ...", "date": "YYYY-MM-DD",
     "machine": {"cpu", "cores", "python", "torch"}, "rows": [{short named figures}],
     "notes": "one line", optional "source" (a transcription's origin) and "plots" (PNG paths)}

Row keys are snake_case and end in their unit (_s, _ms, _db, _mm, _pct, _mb, _gb) when they have one;
values are numbers or short strings, so every table cell stays short.
"""
from __future__ import annotations

import os
import platform
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
KEYS = {"script", "command", "date", "machine", "rows", "notes"}
OPTIONAL = {"source", "plots"}
MACHINE_KEYS = {"cpu", "cores", "python", "torch"}
MAX_CELL = 48     # characters of a string cell
MAX_NOTES = 480   # characters of the one-line notes


def machine() -> dict:
    """CPU model, logical cores, Python and torch versions of this process."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import torch

        tv = torch.__version__
    except ImportError:
        tv = "none"
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "torch": tv}


def rasterizer_built() -> bool:
    """Whether the C++ rasterizer loads; without it the pure-torch twin renders, about 8x slower."""
    from rg_core.render import fast_cpu

    return fast_cpu.available()


BASELINE_DIR = "../baseline"   # where a recorded command checks out the code it compares with


def commit_of(path: Path) -> str:
    """The checkout at `path` as its short commit, '-dirty' when it has changes ('COMMIT' when it is not
    a git checkout): how a record names the code it compared with."""
    import subprocess

    r = subprocess.run(["git", "-C", str(path), "describe", "--always", "--dirty"], capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 and r.stdout.strip() else "COMMIT"


def portable_path(arg: str) -> str:
    """A path argument as anyone can type it in a checkout: relative inside it, and bench_out/<name>
    for a path elsewhere on the machine that recorded it."""
    p = Path(arg)
    if not p.is_absolute():
        return arg
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else f"bench_out/{p.name}"


def command_line(argv: list[str] | None = None) -> str:
    """The command that produced this result, as anyone can run it from the checkout's root (without
    --json / --record): no absolute paths, and a `--baseline-code DIR` comes with the commands that
    check that code out and build its kernels."""
    argv = sys.argv if argv is None else argv
    args, prefix = [a for a in argv[1:] if a not in ("--json", "--record")], ""
    for i, a in enumerate(args):
        if i and args[i - 1] == "--baseline-code":
            prefix = (f"git worktree add {BASELINE_DIR} {commit_of(Path(a)).removesuffix('-dirty')} && "
                      f"(cd {BASELINE_DIR} && python setup.py -q build_ext --inplace) && ")
            args[i] = BASELINE_DIR
        elif a.startswith("/"):
            args[i] = portable_path(a)
    return prefix + " ".join(["python", f"benchmarks/{Path(argv[0]).name}", *args])


def check_result(rec: dict) -> list[str]:
    """Problems of one result record against the schema (empty: it conforms)."""
    bad = []
    if not isinstance(rec, dict):
        return ["not an object"]
    if KEYS - set(rec):
        bad.append(f"missing {sorted(KEYS - set(rec))}")
    if set(rec) - KEYS - OPTIONAL:
        bad.append(f"unknown keys {sorted(set(rec) - KEYS - OPTIONAL)}")
    for k in ("script", "command", "notes", "date"):
        if not isinstance(rec.get(k), str) or (k != "notes" and not rec.get(k)):
            bad.append(f"{k} must be a non-empty string")
    if any(w.startswith(("/", "~")) for w in str(rec.get("command")).split()):
        bad.append("command names an absolute path: write it as anyone runs it from the checkout")
    try:
        time.strptime(str(rec.get("date")), "%Y-%m-%d")
    except ValueError:
        bad.append(f"date {rec.get('date')!r} is not YYYY-MM-DD")
    if "\n" in str(rec.get("notes")) or len(str(rec.get("notes"))) > MAX_NOTES:
        bad.append(f"notes must be one line of at most {MAX_NOTES} characters")
    m = rec.get("machine")
    if not isinstance(m, dict) or set(m) != MACHINE_KEYS:
        bad.append(f"machine must have exactly {sorted(MACHINE_KEYS)}")
    rows = rec.get("rows")
    if not isinstance(rows, list) or not rows:
        bad.append("rows must be a non-empty list")
        rows = []
    for i, r in enumerate(rows):
        if not isinstance(r, dict) or not r:
            bad.append(f"row {i} must be a non-empty object")
            continue
        for k, v in r.items():
            if not (isinstance(k, str) and k.replace("_", "").isalnum() and k == k.lower()):
                bad.append(f"row {i}: key {k!r} is not snake_case")
            if isinstance(v, bool) or not isinstance(v, (int, float, str)) or v is None:
                bad.append(f"row {i}: {k} must be a number or a string")
            elif isinstance(v, str) and (len(v) > MAX_CELL or "\n" in v or "|" in v):
                bad.append(f"row {i}: {k} is longer than {MAX_CELL} characters or has | / a newline")
    if "source" in rec and not str(rec["source"]).startswith("transcribed from the notebook of "):
        bad.append("source must read 'transcribed from the notebook of <date>'")
    if not isinstance(rec.get("plots", []), list):
        bad.append("plots must be a list of paths")
    return bad


def write_result(script: str, rows: list[dict], notes: str, *, command: str | None = None,
                 plots: list | tuple = (), out_dir: Path = RESULTS) -> Path:
    """Write out_dir/<script>.json in the shared schema, dated today, with this machine; PNG plots
    that exist are copied next to it (as <script>-<name>.png) so the docs can point at them."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    kept = []
    for p in map(Path, plots):
        if p.is_file():
            dst = out_dir / f"{script}-{p.name}"
            shutil.copyfile(p, dst)
            kept.append(str(dst.relative_to(ROOT)) if dst.is_relative_to(ROOT) else str(dst))
    load = os.getloadavg()   # the CPU may be shared: say how busy it was
    notes = f"{notes}; load average {load[0]:.1f} (1 min) / {load[1]:.1f} (5 min) at the end, {os.cpu_count()} cores"
    if "rg_core.render" in sys.modules and not rasterizer_built():   # timings about 8x slower: say so
        notes += "; PURE-TORCH RASTERIZER (the C++ kernel was not built)"
    rec = {"script": script, "command": command or command_line(), "date": time.strftime("%Y-%m-%d"),
           "machine": machine(), "rows": rows, "notes": notes}
    if kept:
        rec["plots"] = kept
    bad = check_result(rec)
    if bad:
        raise ValueError(f"{script}: result does not fit the schema: {bad}")
    import json

    path = out_dir / f"{script}.json"
    path.write_text(json.dumps(rec, indent=1) + "\n", encoding="utf-8")
    print(f"recorded {path}", file=sys.stderr)
    return path


def add_output_flags(ap, json_flag: bool = True) -> None:
    """--json (print the script's raw report) and --record (write benchmarks/results/<script>.json)."""
    if json_flag:
        ap.add_argument("--json", action="store_true", help="print the raw report as one JSON line")
    ap.add_argument("--record", action="store_true",
                    help="write benchmarks/results/<script>.json (the source of docs/benchmarks.md)")


def finish(args, report: dict, script: str, to_rows, plots: list | tuple = ()) -> int:
    """The scripts' common ending: print the raw report with --json; with --record turn it into
    (rows, notes) with to_rows(report) and write the shared result file."""
    import json

    if getattr(args, "json", False):
        print(json.dumps(report, default=str))
    if getattr(args, "record", False):
        rows, notes = to_rows(report)
        write_result(script, rows, notes, plots=plots)
    return 0


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, out_png: Path, dpi: int = 110) -> None:
    """Lay out, save (creating the folder) and close a figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=dpi)
    plt.close(fig)


def code_worker(script: str, code: Path, args: list[str], timeout: float, name: str = "") -> dict:
    """Run `script --worker ARGS` in a fresh process with the rg_core of checkout `code` first on its
    path (RG_BENCH_CODE; the script puts it there) -> the JSON object its last stdout line holds."""
    import json
    import subprocess

    env = dict(os.environ, RG_BENCH_CODE=str(code))
    res = subprocess.run([sys.executable, script, "--worker", *args], env=env, capture_output=True, text=True,
                         timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(f"{name} worker ({code}) failed: {res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def rg_json(*args: str, timeout: float = 7200) -> dict:
    """One `rg ... --json --quiet` process (this Python, this checkout's rg_core) -> its JSON, with the
    wall seconds it took as "wall_s"; a failure raises with the end of its stderr."""
    import json
    import subprocess

    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "rg_core.cli", *args, "--json", "--quiet"], capture_output=True,
                         text=True, timeout=timeout)
    if out.returncode != 0:
        raise RuntimeError(f"rg {' '.join(args)} failed ({out.returncode}): {out.stderr[-2000:]}")
    d = json.loads(out.stdout)
    d["wall_s"] = round(time.perf_counter() - t, 1)
    return d
