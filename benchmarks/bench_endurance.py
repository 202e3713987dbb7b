"""Endurance (issue 28): the node fed a looped scene for many frames, a /ground call every 2 s, on
loopback; node RSS, queue, drops and query latency over time (rg_ros/endurance.py).

    python benchmarks/bench_endurance.py [--frames 20000] [--rate 20] [--faults-every 500] [--save-every 5]
                                         [--json] [--record]

The scene: `rg synth` seed 5, 8 views 160x120, 3 objects, replayed by `rg-replay --loop` (stamps keep
increasing); the node: features on, 80 px map, 2 iterations per keyframe, a queue of 4 (frames the
mapper cannot take are dropped and counted, never queued). Faults (rg-replay --faults): after every
500 frames a pose that is not a rotation, a 10-frame pose/TF gap or a 100-frame burst (a stall, then
its frames at once with their capture stamps), in turn; every
5th /ground call goes out with a ~/save_map call. Targets (issue 28): peak RSS growth < 5 %
over the last half of the run, p95 query latency of the last 10 % of the calls within 1.5x of the
first 10 %, no crash, every call answered. Writes endurance.png.
"""
from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # never multicast onto the network
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
from _common import add_output_flags, finish  # noqa: E402


def to_rows(report: dict) -> tuple[list[dict], str]:
    s = report["summary"]
    rows = [{"frames_received": s["frames_received"], "frames_dropped": s["frames_dropped"],
             "queue_max": s["queue_max"], "gaussians": s["gaussians"], "rss_peak_mb": round(s["rss_peak_mb"], 1),
             "rss_growth_last_half_pct": round(s["rss_growth_last_half_pct"], 2), "calls": s["calls"],
             "calls_unanswered": s["calls_unanswered"], "latency_p95_first_s": round(s["latency_p95_first_s"], 3),
             "latency_p95_last_s": round(s["latency_p95_last_s"], 3), "crashed": str(s["crashed"]),
             "run_s": round(s["seconds"], 1),
             "faults": " ".join(f"{k} {v}" for k, v in (s.get("faults_injected") or {}).items()) or "none",
             "frames_rejected_bad_input": s.get("bad_input"), "saves_ok": f"{s.get('saves_ok')}/{s.get('saves')}",
             "keyframes_min": s.get("keyframes_min_after_warmup"), "keyframes_end": s.get("keyframes"),
             **{k: "-" if s.get(k) is None else s[k] for k in ("revisits", "keyframes_replaced", "sync_mixed")}}]
    return rows, (f"{report['frames']} frames at {report['rate']:g} Hz from rg synth seed 5 (8 views 160x120, looped), "
                  f"a /ground call every {report['ground_period']:g} s (3 queries in turn), node features on, 80 px "
                  f"map, queue 4; RSS growth = peak at the end over the peak of the first half; faults every "
                  f"{report.get('faults_every', 0)} frames, a map save with every {report.get('save_every', 0)}th call")


def main() -> int:
    from rg_ros.endurance import EnduranceConfig, plot, run

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20000)
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--ground-period", type=float, default=2.0)
    ap.add_argument("--faults-every", type=int, default=500)
    ap.add_argument("--save-every", type=int, default=5)
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    cfg = EnduranceConfig(frames=args.frames, rate=args.rate, ground_period=args.ground_period,
                          faults_every=args.faults_every, save_every=args.save_every)
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        subprocess.run([sys.executable, "-m", "rg_core.cli", "synth", str(scene), "--views", "8", "--size", "160x120",
                        "--seed", "5", "--objects", "3", "--json", "--quiet"], check=True, capture_output=True)
        result = run(scene, Path(tmp) / "work", cfg)
    png = plot(result, Path(args.out) / "endurance.png", f"{args.frames} frames at {args.rate:g} Hz, /ground every "
               f"{args.ground_period:g} s")
    report = {"frames": args.frames, "rate": args.rate, "ground_period": args.ground_period,
              "faults_every": args.faults_every, "save_every": args.save_every,
              "summary": result["summary"], "calls": result["calls"][-20:]}
    print(report["summary"], file=sys.stderr)
    return finish(args, report, "bench_endurance", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
