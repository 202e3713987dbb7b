"""run_report: every selected section in order, each isolated (a failure is recorded and the next
section runs), then report.md, report.json and the recommended settings."""
from __future__ import annotations

import datetime
import json
import math
import platform
import sys
import time
import traceback
from pathlib import Path

from ..config import GroundConfig
from . import sections_quality as q
from . import sections_system as s
from .budgets import SECTIONS, Budgets
from .context import Context
from .markdown import render

FUNCS = {"mapping": q.mapping, "grounding": q.grounding, "latency": q.latency, "memory": s.memory,
         "savings": q.savings, "scaling": s.scaling, "stability": s.stability, "degraded": q.degraded}


def machine() -> str:
    import os

    import torch

    return (f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}, torch {torch.__version__} "
            f"({torch.get_num_threads()} thread), {datetime.date.today().isoformat()}")


def run_report(scene_dir, out, budgets: Budgets, sections=SECTIONS, cfg=None, progress: bool = True,
               budgets_name: str = "custom") -> dict:
    import torch
    from tqdm import tqdm

    bad = [x for x in sections if x not in FUNCS]
    if bad:
        raise ValueError(f"unknown sections {bad}; known: {','.join(SECTIONS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    threads = torch.get_num_threads()
    torch.set_num_threads(budgets.threads)
    t0 = time.perf_counter()
    try:
        ctx = Context(scene_dir, out, budgets, cfg, progress)
        results = {}
        bar = tqdm([x for x in SECTIONS if x in sections], desc="report", unit="section", file=sys.stderr,
                   disable=not progress)
        for name in bar:
            bar.set_postfix(section=name)
            t = time.perf_counter()
            try:
                results[name] = FUNCS[name](ctx)
            except Exception as exc:  # noqa: BLE001 - one section's failure must not lose the others
                results[name] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=6)}
                ctx.log(f"section {name} failed: {results[name]['error']}")
            results[name]["seconds"] = time.perf_counter() - t
        report = {"scene": str(scene_dir), "machine": machine(), "budgets_name": budgets_name,
                  "seconds": time.perf_counter() - t0, "sections": results}
        try:
            report["recommendations"] = recommend(results)
        except Exception as exc:  # noqa: BLE001 - the tables are still worth writing
            report["recommendations"] = [f"(no recommendation: {type(exc).__name__}: {exc})"]
        report["headline"] = headline(results)
        (out / "report.md").write_text(render(report, out))
        (out / "report.json").write_text(json.dumps(report, indent=1, default=str))
    finally:
        torch.set_num_threads(threads)
    return report


def _ok(results, name):
    r = results.get(name, {})
    return None if "error" in r or not r else r["data"]


def recommend(results: dict) -> list[str]:
    """Settings for a robot that must answer within 1 s, and for one that can wait 10 s."""
    out = []
    lat, grd, sav = _ok(results, "latency"), _ok(results, "grounding"), _ok(results, "savings")
    if grd:
        best = max(r["explicit_amodal"] for r in grd)
        enough = min((r for r in grd if r["explicit_amodal"] >= best - 2), key=lambda r: r["field_seconds"])
        field_txt = (f"train the field for at least {enough['budget']:g} s before answering (explicit amodal mIoU "
                     f"{enough['explicit_amodal']:.1f}%, within 2 points of the best {best:.1f}%)")
        stop = results["grounding"].get("stop")
        if stop:
            field_txt += (f"; the default stop test answered after {stop['field_seconds']:g} s ({stop['steps']} steps, "
                          f"explicit amodal {stop['explicit_amodal']:.1f}%)")
    else:
        field_txt = "train the field for its default budget (the grounding section did not run)"
    for limit in (1.0, 10.0):
        parts = []
        if lat:
            fit = [r for r in lat["rows"] if r["max_s"] <= limit]
            if fit:
                r = max(fit, key=lambda r: r["gaussians"])
                parts.append(f"maps up to {r['gaussians']} Gaussians answer within {limit:g} s (worst query "
                             f"{r['max_s']:.2f} s, median {r['median_s']:.2f} s): keep map.max_gaussians <= {r['gaussians']}")
            else:
                r = min(lat["rows"], key=lambda r: r["gaussians"])
                parts.append(f"no measured map size answers within {limit:g} s (smallest, {r['gaussians']} Gaussians: "
                             f"{r['max_s']:.2f} s): query on a faster machine or a smaller map")
        default_points = GroundConfig().max_cluster_points
        cl = [g for g in (sav or {}).get("grounding", []) if g.get("turned off by") == "max_cluster_points=0"]
        if cl and not math.isnan(cl[0]["seconds off"]):
            c = cl[0]
            if c["seconds off"] <= limit and c["explicit_amodal change"] < 0:
                parts.append(f"max_cluster_points=0 (cluster all: {c['seconds off']:.2f} s/query, "
                             f"{-c['explicit_amodal change']:+.1f} mIoU points)")
            else:
                parts.append(f"max_cluster_points {default_points} (default; clustering all costs "
                             f"{c['seconds off']:.2f} s/query, "
                             f"mIoU change {-c['explicit_amodal change']:+.1f} points)")
        else:
            parts.append(f"max_cluster_points {default_points} (default)")
        parts.append("explicit queries take the rule-based shortcut (mode auto)")
        parts.append(field_txt)
        out.append(f"**Answer within {limit:g} s:** " + "; ".join(parts) + ".")
    return out


def headline(results: dict) -> dict:
    h = {}
    for name in SECTIONS:
        r = results.get(name)
        if r is None:
            continue
        if "error" in r:
            h[name] = {"error": r["error"]}
            continue
        h[name] = (r["data"]["counts"] if name == "stability" else
                   [dict(zip(t["columns"], row)) for t in r["tables"] for row in t["rows"]])
    return h
