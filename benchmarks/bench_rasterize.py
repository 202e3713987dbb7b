"""Rasterizer speed: reference (pure torch) vs fast CPU path, in one run, as medians and ratios.

    python benchmarks/bench_rasterize.py [--repeats 5] [--json] [--baseline-code DIR [--rounds 3]]
                                         [--png bench_out/rasterize.png] [--record]

Cases (a) 20k Gaussians 160x120 and (b) 100k Gaussians 320x240, 36 channels each, on a synthetic
cloud seen by one camera, then a growth check: time against Gaussians x covered pixels.
Peak memory is the process's peak RSS after each stage (ru_maxrss).

--baseline-code DIR: a checkout of older code with its kernels built (`python setup.py build_ext
--inplace` there); each case is timed in fresh processes that alternate between that code and this
one, `--rounds` times, and the medians are reported with the ratio new / baseline (the machine may
be shared: the ratio is the figure to trust).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
# the code under test: this checkout, or a baseline's (worker processes, --baseline-code)
sys.path.insert(0, os.environ.get("RG_BENCH_CODE") or str(ROOT))
from rg_core.render import Camera, rasterize  # noqa: E402
from rg_core.util import peak_rss_mb  # noqa: E402
from _common import add_output_flags, code_worker, finish, pyplot, save_figure  # noqa: E402

CASES = {"a_20k_160x120": (20_000, 160, 120), "b_100k_320x240": (100_000, 320, 240)}


def make_scene(n: int, width: int, height: int, channels: int, seed: int = 0, scale: float = 1.0):
    """Gaussians in a 1.2 x 0.9 x 0.6 m box 3 m in front of a camera with a ~58 degree field of view."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.6, 0.45, 0.3]) + torch.tensor([0.0, 0.0, 3.0])
    scales = (torch.rand(n, 3, generator=g) * 0.03 + 0.005) * scale
    quats = torch.randn(n, 4, generator=g)
    opac = torch.rand(n, generator=g) * 0.9 + 0.05
    feats = torch.rand(n, channels, generator=g)
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2 - 0.5], [0.0, f, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return (means, scales, quats, opac, feats), Camera(K, torch.eye(4), width, height, 0.05, 50.0)


def time_backend(params, cam, backend: str, repeats: int) -> dict:
    leaves = [p.clone().requires_grad_(True) for p in params]
    weights = torch.linspace(0, 1, params[4].shape[1])

    def fwd():
        with torch.no_grad():
            return rasterize(*leaves, cam, backend=backend)

    def fwd_bwd():
        for p in leaves:
            p.grad = None
        r = rasterize(*leaves, cam, backend=backend)
        ((r.channels * weights).sum() + r.depth.sum() + r.alpha.sum()).backward()
        return r

    res = {}
    for name, fn in (("forward_ms", fwd), ("forward_backward_ms", fwd_bwd)):
        fn()  # warm-up
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            ts.append((time.perf_counter() - t) * 1000.0)
        res[name] = round(statistics.median(ts), 2)
    out = fwd()
    res["covered_pixels"] = int((out.alpha > 0.01).sum())
    res["peak_rss_mb"] = round(peak_rss_mb(), 1)
    return res


def worker(label: str, repeats: int) -> dict:
    """One case on the fast path of the code in sys.path[0] (a fresh process per call)."""
    n, w, h = CASES[label]
    params, cam = make_scene(n, w, h, 36)
    return time_backend(params, cam, "cpu", repeats)


def against_baseline(base: Path, rounds: int, repeats: int) -> dict:
    """Fresh processes alternating baseline / new code per case; medians over rounds and the ratio."""
    out = {}
    for label in CASES:
        runs = {"baseline": [], "new": []}
        for r in range(rounds):
            for name, code in (("baseline", base), ("new", ROOT)):
                runs[name].append(code_worker(__file__, code, [label, "--repeats", str(repeats)], 900, name))
        med = {name: {k: round(statistics.median(x[k] for x in rs), 2) for k in ("forward_ms", "forward_backward_ms")}
               for name, rs in runs.items()}
        out[label] = {**med, "rounds": rounds,
                      "ratio_forward": round(med["new"]["forward_ms"] / med["baseline"]["forward_ms"], 3),
                      "ratio_forward_backward": round(med["new"]["forward_backward_ms"]
                                                      / med["baseline"]["forward_backward_ms"], 3)}
        print(f"{label}: baseline fwd {med['baseline']['forward_ms']} / fwd+bwd {med['baseline']['forward_backward_ms']}"
              f" ms, new {med['new']['forward_ms']} / {med['new']['forward_backward_ms']} ms: ratio new/baseline "
              f"{out[label]['ratio_forward']} / {out[label]['ratio_forward_backward']} (medians of {rounds} "
              "alternating runs)", file=sys.stderr)
    return out


def to_rows(report: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: one per case (fast path, reference, speed-up; ratio to a baseline if run)."""
    rows = []
    for label, c in report["cases"].items():
        n, w, h = CASES[label]
        row = {"case": f"{n // 1000}k Gaussians, {w}x{h}", "fwd_ms": c["fast"]["forward_ms"],
               "fwd_bwd_ms": c["fast"]["forward_backward_ms"], "reference_fwd_ms": c["reference"]["forward_ms"],
               "reference_fwd_bwd_ms": c["reference"]["forward_backward_ms"],
               "speedup": f"x{c['speedup_forward']} / x{c['speedup_forward_backward']}",
               "peak_rss_mb": c["reference"]["peak_rss_mb"]}
        if "baseline" in report:
            b = report["baseline"][label]
            row["ratio_to_baseline"] = f"{b['ratio_forward']} / {b['ratio_forward_backward']}"
        rows.append(row)
    return rows, (f"36 channels, {report['threads']} torch threads; speed-up = reference / fast (fwd / fwd+bwd); "
                  f"fwd+bwd time ~ (Gaussians x covered pixels)^{report['growth']['exponent_vs_gaussians_x_pixels']}")


def plot(report: dict, path: Path) -> None:
    plt = pyplot()
    labels = list(report["cases"])
    fig, axes = plt.subplots(1, len(labels), figsize=(5 * len(labels), 3.6))
    for ax, label in zip(axes, labels):
        c = report["cases"][label]
        bars = {"fast": c["fast"]}
        if "baseline" in report:
            bars = {"baseline": report["baseline"][label]["baseline"], "new": report["baseline"][label]["new"]}
        names = list(bars)
        for i, key in enumerate(("forward_ms", "forward_backward_ms")):
            vals = [bars[k][key] for k in names]
            xs = [j + 0.38 * i for j in range(len(names))]
            ax.bar(xs, vals, width=0.36, label=key.replace("_ms", "").replace("_", "+"))
            for x, v in zip(xs, vals):
                ax.text(x, v, f"{v:.0f}", ha="center", va="bottom", fontsize=8)
        ax.set_xticks([j + 0.19 for j in range(len(names))], names)
        ax.set_ylabel("ms (median)")
        ax.set_title(label)
        ax.legend(fontsize=8)
    fig.suptitle(f"fast CPU rasterizer, 36 channels, {report['threads']} threads")
    save_figure(fig, path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ref-repeats", type=int, default=1, help="repeats for the slow reference")
    ap.add_argument("--baseline-code", help="checkout of older code (kernels built in place) to compare with")
    ap.add_argument("--rounds", type=int, default=3, help="alternating baseline/new runs per case")
    ap.add_argument("--png", default="", help="bar chart of the timings")
    ap.add_argument("--worker", choices=list(CASES), help=argparse.SUPPRESS)
    add_output_flags(ap)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.repeats)))
        return 0
    report = {"threads": torch.get_num_threads(), "cases": {}}
    if args.baseline_code:
        report["baseline"] = against_baseline(Path(args.baseline_code).resolve(), args.rounds, args.repeats)
    for label, (n, w, h) in CASES.items():
        params, cam = make_scene(n, w, h, 36)
        fast = time_backend(params, cam, "cpu", args.repeats)
        ref = time_backend(params, cam, "reference", args.ref_repeats)
        report["cases"][label] = {
            "fast": fast, "reference": ref,
            "speedup_forward": round(ref["forward_ms"] / fast["forward_ms"], 1),
            "speedup_forward_backward": round(ref["forward_backward_ms"] / fast["forward_backward_ms"], 1),
        }
        print(f"{label}: fast fwd {fast['forward_ms']} ms, fwd+bwd {fast['forward_backward_ms']} ms | "
              f"reference fwd {ref['forward_ms']} ms, fwd+bwd {ref['forward_backward_ms']} ms | speed-up "
              f"x{report['cases'][label]['speedup_forward']} / x{report['cases'][label]['speedup_forward_backward']}"
              f" | peak RSS {ref['peak_rss_mb']} MB", file=sys.stderr)
    # Growth: Gaussians x covered pixels against forward+backward time (fast path only).
    growth = []
    for n, w, h in ((10_000, 160, 120), (20_000, 160, 120), (40_000, 160, 120), (20_000, 320, 240),
                    (40_000, 320, 240), (80_000, 320, 240)):
        params, cam = make_scene(n, w, h, 36)
        r = time_backend(params, cam, "cpu", args.repeats)
        growth.append({"gaussians": n, "size": [w, h], "gauss_x_pixels": n * r["covered_pixels"],
                       "forward_backward_ms": r["forward_backward_ms"]})
    import math

    xs = [math.log(g["gauss_x_pixels"]) for g in growth]
    ys = [math.log(g["forward_backward_ms"]) for g in growth]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)
    report["growth"] = {"points": growth, "exponent_vs_gaussians_x_pixels": round(slope, 3)}
    print(f"growth exponent of fwd+bwd time vs Gaussians x covered pixels: {slope:.3f}", file=sys.stderr)
    report["peak_rss_mb"] = round(peak_rss_mb(), 1)
    if args.png:
        plot(report, Path(args.png))
        print(f"plot: {args.png}", file=sys.stderr)
    return finish(args, report, "bench_rasterize", to_rows, plots=[args.png] if args.png else [])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
