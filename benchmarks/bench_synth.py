"""`rg synth` speed: 100 views, 320x240, 7 objects, with 1 and 2 render workers in one run.

    python benchmarks/bench_synth.py [--views 100] [--json] [--record]

The 1-worker run is the baseline; the ratio is the parallel speed-up. Target: under 60 s on the
2-core machine.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from rg_core.config import SynthConfig  # noqa: E402
from rg_core.synth.generator import default_objects_dir, generate_scene  # noqa: E402
from _common import add_output_flags, finish  # noqa: E402


def to_rows(res: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: one per worker count."""
    rows = [{"workers": w, "views": res["views"], "time_s": res[f"seconds_{w}_worker"]} for w in (1, 2)]
    rows[1]["speedup"] = f"x{res['speedup_2_workers']}"
    return rows, "320x240, 7 objects, seed 0; output byte-identical with 1 and 2 workers: " + ("yes" if res["identical_output"] else "NO")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=100)
    add_output_flags(ap)
    args = ap.parse_args()
    res = {"views": args.views}
    with tempfile.TemporaryDirectory() as tmp:
        for workers in (1, 2):
            cfg = SynthConfig(views=args.views, width=320, height=240, objects=7, seed=0, workers=workers)
            t = time.perf_counter()
            generate_scene(Path(tmp) / f"w{workers}", cfg, default_objects_dir(), progress=False)
            res[f"seconds_{workers}_worker"] = round(time.perf_counter() - t, 2)
            print(f"{args.views} views 320x240, 7 objects, {workers} worker(s): {res[f'seconds_{workers}_worker']} s",
                  file=sys.stderr)
        a = (Path(tmp) / "w1").rglob("*")
        same = all(p.read_bytes() == (Path(tmp) / "w2" / p.relative_to(Path(tmp) / "w1")).read_bytes()
                   for p in a if p.is_file())
    res["speedup_2_workers"] = round(res["seconds_1_worker"] / res["seconds_2_worker"], 2)
    res["identical_output"] = same
    print(f"speed-up with 2 workers: x{res['speedup_2_workers']}, identical output: {same}", file=sys.stderr)
    return finish(args, res, "bench_synth", to_rows)


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
