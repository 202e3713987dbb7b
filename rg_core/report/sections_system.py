"""Report sections on the system: peak memory and time against frames and image size (each point a
fresh process), and the numerical-stability tests of the suite (pytest junit XML)."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from .plots import line_plot
from .scaling import growth_exponent, run_point
from .sections_quality import _table


def _map_over(ctx) -> dict:
    return {k: v for k, v in dataclasses.asdict(ctx.cfg.map).items() if k != "width"}


def frames_runs(ctx) -> list[dict]:
    """Mapping time and peak RSS for the first n frames (cached: memory and scaling share it)."""
    if "frames_runs" in ctx.cache:
        return ctx.cache["frames_runs"]
    if any(n < 1 for n in ctx.b.frames):
        raise ValueError(f"frame counts must be >= 1, got {ctx.b.frames}")
    need = max(ctx.b.frames)
    scene_dir = ctx.scene_dir
    w, h = ctx.scene.train[0].intrinsics.width, ctx.scene.train[0].intrinsics.height
    if len(ctx.scene.frames) < need:
        scene_dir = ctx.synth_scene(need, w, h)
    width = min(ctx.cfg.map.width, w)
    rows = []
    for n in sorted(ctx.b.frames):
        rows.append(run_point(scene_dir, n, width, _map_over(ctx), ctx.b.threads, fresh=ctx.b.fresh_process))
        ctx.log(f"frames {n}: {rows[-1]}")
    ctx.cache["frames_runs"] = rows
    return rows


def memory(ctx) -> dict:
    """Peak resident memory against frames streamed (each count in a fresh process)."""
    rows = frames_runs(ctx)
    own = len(ctx.scene.train)
    near = min(rows, key=lambda r: abs(r["frames"] - own))
    k = growth_exponent([r["frames"] for r in rows], [r["peak_rss_mb"] - r["rss_before_mb"] for r in rows])
    png = line_plot(ctx.plots / "memory_vs_frames.png", [
        {"x": "frames streamed", "y": "peak RSS (MB)", "series": [
            ("peak RSS", [r["frames"] for r in rows], [r["peak_rss_mb"] for r in rows]),
            ("after imports", [r["frames"] for r in rows], [r["rss_before_mb"] for r in rows])],
         "mark": [(near["frames"], near["peak_rss_mb"], f"default settings, ~this scene ({own} frames)")]}],
        "Peak memory against frames (default map settings, no final refinement)")
    cols = ("frames", "width", "seconds", "keyframes", "Gaussians", "peak RSS MB", "RSS after imports MB")
    t = [(r["frames"], r["width"], r["seconds"], r["keyframes"], r["gaussians"], r["peak_rss_mb"], r["rss_before_mb"]) for r in rows]
    return {"text": [f"Growth exponent of (peak - after imports) RSS against frames: {k:.2f}."],
            "tables": [_table("Peak memory against frames", cols, t)], "plots": [png], "data": {"rows": rows, "exponent": k}}


def scaling(ctx) -> dict:
    """Time and memory against frames and image size, with log-log growth exponents."""
    fr = frames_runs(ctx)
    sz = []
    for w, h in ctx.b.sizes:
        if w < 8 or h < 8:
            raise ValueError(f"image sizes must be at least 8x8, got {w}x{h}")
        d = ctx.synth_scene(ctx.b.size_views, w, h)
        sz.append({**run_point(d, ctx.b.size_views, w, _map_over(ctx), ctx.b.threads, fresh=ctx.b.fresh_process), "height": h, "pixels": w * h})
        ctx.log(f"size {w}x{h}: {sz[-1]}")
    ex = {"time_vs_frames": growth_exponent([r["frames"] for r in fr], [r["seconds"] for r in fr]),
          "memory_vs_frames": growth_exponent([r["frames"] for r in fr], [r["peak_rss_mb"] - r["rss_before_mb"] for r in fr]),
          "time_vs_pixels": growth_exponent([r["pixels"] for r in sz], [r["seconds"] for r in sz]),
          "memory_vs_pixels": growth_exponent([r["pixels"] for r in sz], [r["peak_rss_mb"] - r["rss_before_mb"] for r in sz])}
    dw = ctx.cfg.map.width
    mark_sz = [(r["pixels"], r["seconds"], "default width") for r in sz if r["width"] == dw]
    png = line_plot(ctx.plots / "scaling.png", [
        {"x": "frames", "y": "seconds", "logx": True, "logy": True,
         "series": [("mapping time", [r["frames"] for r in fr], [r["seconds"] for r in fr])]},
        {"x": "pixels per frame", "y": "seconds", "logx": True, "logy": True, "mark": mark_sz,
         "series": [("mapping time", [r["pixels"] for r in sz], [r["seconds"] for r in sz])]},
        {"x": "pixels per frame", "y": "peak RSS - after imports (MB)", "logx": True, "logy": True,
         "series": [("memory", [r["pixels"] for r in sz], [max(r["peak_rss_mb"] - r["rss_before_mb"], 1e-3) for r in sz])]}],
        "Scaling: time and memory against frames and image size (log-log)")
    cols = ("size", "frames", "seconds", "keyframes", "Gaussians", "peak RSS MB", "RSS after imports MB")
    t = [(f"{r['width']}x{r['height']}", r["frames"], r["seconds"], r["keyframes"], r["gaussians"], r["peak_rss_mb"],
          r["rss_before_mb"]) for r in sz]
    if not ctx.b.fresh_process:  # one process: its peak memory only ever grows, no per-point figure
        ex.update(memory_vs_frames="n/a (in-process run)", memory_vs_pixels="n/a (in-process run)")
    et = [(k.replace("_", " "), v) for k, v in ex.items()]
    return {"text": ["Image-size scenes are mapped at full width (map.width = image width); frame counts at "
                     "min(map.width, image width). Each point is a fresh process, no final refinement."],
            "tables": [_table("Time and memory against image size", cols, t),
                       _table("Growth exponents (log-log fit, y ~ x^k)", ("fit", "k"), et)],
            "plots": [png], "data": {"frames": fr, "sizes": sz, "exponents": ex}}


def stability(ctx) -> dict:
    """Stiff and extreme cases of the test suite (collected and run by pytest, junit XML)."""
    repo = Path(__file__).resolve().parents[2]
    files = [f for f in ctx.b.stability_files if (repo / f).is_file()]
    if not files:
        raise FileNotFoundError(f"none of {list(ctx.b.stability_files)} exists under {repo} (tests are not installed)")
    xml = ctx.out / "stability_junit.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *files, "-k", ctx.b.stability_k,
           f"--junitxml={xml}"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    p = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True, timeout=1800)
    if not xml.is_file():
        raise RuntimeError(f"pytest wrote no junit XML (exit {p.returncode}): {p.stdout[-500:]}{p.stderr[-500:]}")
    rows = []
    for tc in ET.parse(xml).getroot().iter("testcase"):
        out = "passed"
        for tag in ("failure", "error", "skipped"):
            if tc.find(tag) is not None:
                out = {"failure": "failed", "error": "error", "skipped": "skipped"}[tag]
        doc = tc.get("classname", "").split(".")[-1]
        rows.append((doc, tc.get("name", ""), out, float(tc.get("time", 0.0))))
    counts = {o: sum(r[2] == o for r in rows) for o in ("passed", "failed", "error", "skipped")}
    return {"text": [f"`pytest {' '.join(files)} -k \"{ctx.b.stability_k}\"`: " +
                     ", ".join(f"{v} {k}" for k, v in counts.items() if v) + ". Each test asserts finite outputs "
                     "(and, where it compares, agreement within its tolerance) on the stiff or extreme input its name says."],
            "tables": [_table("Numerical stability tests", ("module", "test", "outcome", "seconds"), rows)],
            "plots": [], "data": {"counts": counts, "exit": p.returncode}}
