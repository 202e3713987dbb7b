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
import json
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


def busy_map(scene: Path, out: Path, n: int) -> Path:
    """The endurance scene mapped, supervised with the default models and its field trained as the
    node does, then tiled to `n` Gaussians (report.inputs.resized_map): a room-size start-up map."""
    from rg_core.config import FieldConfig, MapConfig, RGConfig
    from rg_core.field import FeatureField
    from rg_core.grounding.pipeline import Grounder
    from rg_core.io.captures import read_scene
    from rg_core.map.mapper import Mapper
    from rg_core.map.run import stream_frames
    from rg_core.map.store import save_map
    from rg_core.perception.embed import make_embedder
    from rg_core.perception.masks import make_mask_generator
    from rg_core.perception.supervision import supervise_map_multiview
    from rg_core.report.inputs import resized_map

    m = Mapper(MapConfig(width=80, iters_per_keyframe=2))
    stream_frames(m, read_scene(scene, test_every=0).train, progress=False)
    supervise_map_multiview(m, make_mask_generator("rgbd"), make_embedder("conse"),
                            views_per_object=RGConfig().models.views_per_object)
    f = FeatureField(m, FieldConfig())
    f.train(seconds=10.0, converge=True)
    mm, ff = resized_map(m, f, n, tile=True)
    mm.frames_seen = m.frames_seen
    Grounder(mm, ff, RGConfig()).store_texts()
    return save_map(mm, out / f"busy_{n}.rgmap")


def busy(args, scene: Path, tmp: Path) -> dict:
    """Issue 62: mapping at `rate` Hz, a /ground call every second and a ~/save_map every 10 s, on
    the scene's own map (~600 Gaussians) and on a 100k one; the same without queries (throughput),
    and the baseline code's node under the same load (memory, latency before)."""
    from rg_ros.endurance import EnduranceConfig, run

    frames = int(args.rate * args.seconds)
    runs = {}
    maps = {"small": ""}
    if not args.small_only:
        maps["100k"] = str(busy_map(scene, tmp, 100_000))
    for size, path in maps.items():
        extra = {"load_map": path} if path else {}
        plan = [("queries", "", 1.0, 10.0), ("no_queries", "", 0.0, 0.0)]
        if args.baseline_code:
            plan.append(("baseline", str(Path(args.baseline_code).resolve()), 1.0, 10.0))
        for label, code, gp, sp in plan:
            cfg = EnduranceConfig(frames=frames, rate=args.rate, ground_period=gp, save_period=sp, code_dir=code,
                                  faults_every=0)
            cfg.params.update(extra)
            print(f"busy map: {size} {label} ({frames} frames)", file=sys.stderr)
            r = run(scene, tmp / f"work_{size}_{label}", cfg)
            runs[f"{size}/{label}"] = {"summary": r["summary"], "saves": r["saves"][-5:], "calls": r["calls"][-5:],
                                       "latencies": [c["seconds"] for c in r["calls"]]}
            print(json.dumps({k: r["summary"][k] for k in ("gaussians", "calls", "calls_unanswered", "latency_p50_s",
                                                            "latency_p95_s", "latency_max_s", "mapped_per_s",
                                                            "rss_peak_mb", "periodic_saves_ok")}), file=sys.stderr)
    return {"busy": True, "rate": args.rate, "seconds": args.seconds, "baseline_code": args.baseline_code,
            "baseline_commit": _commit(args.baseline_code) if args.baseline_code else "", "runs": runs}


def _commit(path: str) -> str:
    r = subprocess.run(["git", "-C", path, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return r.stdout.strip()


def busy_rows(report: dict) -> tuple[list[dict], str]:
    rows = []
    runs = report["runs"]
    for key, r in runs.items():
        size, label = key.split("/")
        s = r["summary"]
        ref = runs.get(f"{size}/no_queries", {}).get("summary", {})
        base = runs.get(f"{size}/baseline", {}).get("summary", {})
        rows.append({"map": size, "run": label, "gaussians": s["gaussians"], "calls": s["calls"],
                     "unanswered": s["calls_unanswered"],
                     **{k: round(s[k], 3) for k in ("latency_p50_s", "latency_p95_s", "latency_max_s")},
                     "calls_during_save": s["calls_during_save"],
                     "saves_ok": f"{s['periodic_saves_ok']}/{s['periodic_saves']}",
                     "mapped_per_s": round(s["mapped_per_s"], 2),
                     "throughput_vs_no_queries": round(s["mapped_per_s"] / ref["mapped_per_s"], 3)
                     if ref.get("mapped_per_s") else "-",
                     "rss_peak_mb": round(s["rss_peak_mb"], 1),
                     "rss_vs_baseline": round(s["rss_peak_mb"] / base["rss_peak_mb"], 3)
                     if base.get("rss_peak_mb") and label != "baseline" else "-"})
    return rows, (f"issue 62: mapping at {report['rate']:g} Hz for {report['seconds']:g} s (rg synth seed 5 looped, "
                  f"features on, 80 px map, queue 4), a /ground call every second and a ~/save_map every 10 s from a "
                  f"second client; 'no_queries': the same without either (throughput reference); 'baseline': the "
                  f"node of commit {report.get('baseline_commit') or '-'} under the same load (RSS reference). "
                  f"'100k': the node starts from the scene's map tiled to 100k Gaussians")


def main() -> int:
    from rg_ros.endurance import EnduranceConfig, plot, run

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--busy", action="store_true", help="issue 62's protocol: a query every second and a save every "
                    "10 s while mapping, on ~600 and 100k Gaussians, against no queries and --baseline-code")
    ap.add_argument("--seconds", type=float, default=120.0, help="--busy: seconds of mapping per run")
    ap.add_argument("--baseline-code", default="", help="--busy: a checkout of the code to compare with "
                    "(git worktree add ../baseline <commit>; its rg_core/_C*.so copied in)")
    ap.add_argument("--small-only", action="store_true", help="--busy: only the ~600-Gaussian map")
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
        if args.busy:
            report = busy(args, scene, Path(tmp))
            png = plot_busy(report, Path(args.out) / "busy_map.png")
            return finish(args, report, "bench_busy_map", busy_rows, plots=[png])
        result = run(scene, Path(tmp) / "work", cfg)
    png = plot(result, Path(args.out) / "endurance.png", f"{args.frames} frames at {args.rate:g} Hz, /ground every "
               f"{args.ground_period:g} s")
    report = {"frames": args.frames, "rate": args.rate, "ground_period": args.ground_period,
              "faults_every": args.faults_every, "save_every": args.save_every,
              "summary": result["summary"], "calls": result["calls"][-20:]}
    print(report["summary"], file=sys.stderr)
    return finish(args, report, "bench_endurance", to_rows, plots=[png])


def plot_busy(report: dict, png: Path) -> Path:
    """/ground latency per run (box plot) against the 0.3 s target."""
    from _common import pyplot

    plt = pyplot()
    runs = {k: [x for x in r["latencies"] if x is not None] for k, r in report["runs"].items() if r["latencies"]}
    fig, ax = plt.subplots(figsize=(8, 3.4))
    ax.boxplot(list(runs.values()), whis=(5, 95))
    ax.set_xticks(range(1, len(runs) + 1), list(runs), fontsize=8)
    ax.axhline(0.3, color="r", lw=0.8, ls="--", label="p95 target 0.3 s")
    ax.axhline(1.0, color="k", lw=0.8, ls=":", label="max target 1.0 s")
    ax.set_yscale("log")
    ax.set_ylabel("/ground latency (s)")
    ax.legend(fontsize=7)
    ax.set_title(f"/ground while mapping at {report['rate']:g} Hz with a save every 10 s", fontsize=9)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return png


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
