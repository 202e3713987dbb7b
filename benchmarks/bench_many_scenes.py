"""Many scenes (issue 64): `rg synth --seeds` and `rg eval` over a handful of tiny scenes one after
another in one process (the baseline, measured in the same run) against `--ray --workers W` on the
same machine; whether every scene's figures are the same both ways; and the driver's peak RSS on Ray
for those scenes and for 100 (the driver must not grow with the number of scenes).

    python benchmarks/bench_many_scenes.py [--scenes 10] [--workers 2] [--memory-scenes 100]
                                           [--out bench_out/many_scenes] [--json] [--record]

Scenes: `rg synth` 8 views of 64x48, 3 objects (seeds 1..N); eval: oracle supervision, 5 field steps,
1 implicit and 2 relational queries per scene, map width 64 (the test suite's settings: the figures
are the engines', not the pipeline's). Throughput: scenes per minute of the whole command, Ray's
start-up included: Ray's start (about 5 s) and each worker's first scene (imports, models: about 10 s)
are paid once per run, so the fewer the scenes the less Ray gains (6 scenes measured x0.95 on a
loaded machine, 10 x1.2). The memory runs list the N scenes over and over under distinct names
(symlinks), so 100 scenes cost 100 evaluations but only N syntheses.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _common import add_output_flags, finish  # noqa: E402

SYNTH = ["--views", "8", "--size", "64x48", "--objects", "3"]
EVAL = ["--supervision", "oracle", "--field-steps", "5", "--implicit", "1", "--relational", "2",
        "--map.width", "64", "--map.iters_per_keyframe", "1", "--map.final_iters", "0", "--field.rays_per_step", "64"]


def rg(*args) -> tuple[dict, float]:
    """`rg ... --json --quiet` -> (its JSON, wall seconds)."""
    import subprocess

    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "rg_core.cli", *map(str, args), "--json", "--quiet"],
                       capture_output=True, text=True, timeout=7200)
    if r.returncode != 0:
        raise RuntimeError(f"rg {' '.join(map(str, args))} failed: {r.stderr[-2000:]}")
    return json.loads(r.stdout), time.perf_counter() - t


def figures(agg: dict) -> dict:
    """scene -> its figures but seconds, as sorted JSON (NaN equals NaN)."""
    return {s["scene"]: json.dumps({k: v for k, v in (s["eval"] or {}).items() if k != "seconds"}, sort_keys=True)
            for s in agg["scenes"]}


def same_bytes(a: Path, b: Path) -> bool:
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and ".rg_synth" not in p.parts)
    return files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file() and ".rg_synth" not in p.parts) \
        and all((a / f).read_bytes() == (b / f).read_bytes() for f in files)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--memory-scenes", type=int, nargs="*", default=[100])
    ap.add_argument("--out", default="bench_out/many_scenes")
    add_output_flags(ap)
    args = ap.parse_args()
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    seeds = f"1-{args.scenes}"
    ray = ["--ray", "--workers", str(args.workers)]
    rep: dict = {"scenes": args.scenes, "workers": args.workers, "cores": len(os.sched_getaffinity(0))}
    s_seq, rep["synth_seq_s"] = rg("synth", out / "seq", "--seeds", seeds, *SYNTH)
    s_ray, rep["synth_ray_s"] = rg("synth", out / "ray", "--seeds", seeds, *SYNTH, *ray)
    rep["synth_same_bytes"] = same_bytes(out / "seq", out / "ray")
    rep["synth_ok"] = [s_seq["scenes"]["ok"], s_ray["scenes"]["ok"]]
    e_seq, rep["eval_seq_s"] = rg("eval", out / "seq", "--results", out / "r_seq", *EVAL)
    e_ray, rep["eval_ray_s"] = rg("eval", out / "seq", "--results", out / "r_ray", *EVAL, *ray)
    f_seq, f_ray = figures(e_seq), figures(e_ray)
    rep["eval_ok"] = [e_seq["aggregate"]["scenes"]["ok"], e_ray["aggregate"]["scenes"]["ok"]]
    rep["figures_equal"] = sum(f_ray.get(n) == f for n, f in f_seq.items())
    rep["driver_rss_mb"] = {"local": e_seq["run"]["driver_peak_rss_mb"], "ray": e_ray["run"]["driver_peak_rss_mb"]}
    rep["aggregate"] = {k: e_seq["aggregate"][k] for k in ("explicit", "implicit", "relational", "all") if k in e_seq["aggregate"]}
    scenes = sorted(p for p in (out / "seq").iterdir() if p.is_dir() and not p.name.startswith("."))
    rep["memory"] = [{"scenes": args.scenes, "ok": rep["eval_ok"][1], "wall_s": round(rep["eval_ray_s"], 1),
                      "driver_peak_rss_mb": e_ray["run"]["driver_peak_rss_mb"]}]
    for m in args.memory_scenes:
        d = out / f"mem{m}"
        d.mkdir()
        for i in range(m):
            (d / f"m{i:05d}").symlink_to(scenes[i % len(scenes)].resolve())
        agg, wall = rg("eval", d, "--results", out / f"r_mem{m}", *EVAL, *ray)
        rep["memory"].append({"scenes": m, "ok": agg["aggregate"]["scenes"]["ok"], "wall_s": round(wall, 1),
                              "driver_peak_rss_mb": agg["run"]["driver_peak_rss_mb"]})
    print(summary(rep), file=sys.stderr)
    return finish(args, rep, "bench_many_scenes", to_rows)


def summary(rep: dict) -> str:
    n = rep["scenes"]
    lines = [f"{n} tiny scenes, {rep['workers']} Ray workers on {rep['cores']} cores:",
             f"  synth: sequential {rep['synth_seq_s']:.1f} s, ray {rep['synth_ray_s']:.1f} s "
             f"(throughput x{rep['synth_seq_s'] / rep['synth_ray_s']:.2f}), same bytes: {rep['synth_same_bytes']}",
             f"  eval:  sequential {rep['eval_seq_s']:.1f} s, ray {rep['eval_ray_s']:.1f} s "
             f"(throughput x{rep['eval_seq_s'] / rep['eval_ray_s']:.2f}), figures equal in {rep['figures_equal']} of {n}",
             f"  driver peak RSS: sequential {rep['driver_rss_mb']['local']} MB, ray {rep['driver_rss_mb']['ray']} MB"]
    lines += [f"  ray, {m['scenes']} scenes: driver peak RSS {m['driver_peak_rss_mb']} MB ({m['ok']} ok, {m['wall_s']} s)"
              for m in rep["memory"]]
    return "\n".join(lines)


def to_rows(rep: dict) -> tuple[list[dict], str]:
    n, w = rep["scenes"], rep["workers"]
    rows = []
    for what, seq, on_ray in (("synth", rep["synth_seq_s"], rep["synth_ray_s"]), ("eval", rep["eval_seq_s"], rep["eval_ray_s"])):
        rows.append({"run": f"{what}, sequential", "scenes": n, "wall_s": round(seq, 1),
                     "scenes_per_min": round(60 * n / seq, 1), "throughput_x": 1.0})
        row = {"run": f"{what}, ray {w} workers", "scenes": n, "wall_s": round(on_ray, 1),
               "scenes_per_min": round(60 * n / on_ray, 1), "throughput_x": round(seq / on_ray, 2),
               "same_as_sequential": ("bytes equal" if rep["synth_same_bytes"] else "BYTES DIFFER") if what == "synth"
               else f"figures equal {rep['figures_equal']} of {n}"}
        if what == "eval":
            row["driver_peak_rss_mb"] = rep["driver_rss_mb"]["ray"]
        rows.append(row)
    rows.append({"run": "eval, sequential: driver", "scenes": n, "driver_peak_rss_mb": rep["driver_rss_mb"]["local"]})
    for m in rep["memory"][1:]:
        rows.append({"run": f"eval, ray {w} workers: driver", "scenes": m["scenes"], "wall_s": m["wall_s"],
                     "scenes_per_min": round(60 * m["scenes"] / m["wall_s"], 1),
                     "driver_peak_rss_mb": m["driver_peak_rss_mb"]})
    a = rep["aggregate"].get("all", {})
    notes = (f"tiny rg synth scenes (8 views 64x48, 3 objects), oracle supervision, 5 field steps; throughput of the "
             f"whole command (Ray's start-up included) against the sequential run of the same script; pooled over "
             f"the {n} scenes: mIoU {a.get('miou')}, AUROC {a.get('auroc')}")
    return rows, notes


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
