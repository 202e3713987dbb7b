"""Rasterizer speed: reference (pure torch) vs fast CPU path, in one run, as medians and ratios.

    python benchmarks/bench_rasterize.py [--repeats 5] [--json]

Cases (a) 20k Gaussians 160x120 and (b) 100k Gaussians 320x240, 36 channels each, on a synthetic
cloud seen by one camera, then a growth check: time against Gaussians x covered pixels.
Peak memory is the process's peak RSS after each stage (ru_maxrss).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from rg_core.render import Camera, rasterize  # noqa: E402
from rg_core.util import peak_rss_mb  # noqa: E402


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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ref-repeats", type=int, default=1, help="repeats for the slow reference")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    report = {"threads": torch.get_num_threads(), "cases": {}}
    for label, n, w, h in (("a_20k_160x120", 20_000, 160, 120), ("b_100k_320x240", 100_000, 320, 240)):
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
    if args.json:
        print(json.dumps(report))
    return 0


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
