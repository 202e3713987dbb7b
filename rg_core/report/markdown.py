"""report.md from the sections' data: one header per section, tables, plots, or the error."""
from __future__ import annotations

import math
from pathlib import Path

TITLES = {"mapping": "Mapping: error against run time", "grounding": "Grounding: mIoU against feature-training time",
          "latency": "Query latency against map size", "memory": "Peak memory against frames",
          "savings": "Savings: what each shortcut buys", "scaling": "Scaling: time and memory against frames and image size",
          "stability": "Numerical stability", "degraded": "Degraded inputs"}


def fmt(v) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        a = abs(v)
        return f"{v:.0f}" if a >= 1000 else f"{v:.2f}" if a >= 1 else f"{v:.4f}" if a >= 1e-3 or a == 0 else f"{v:.2e}"
    return str(v).replace("|", "/")


def table(t: dict) -> list[str]:
    lines = [f"**{t['title']}**", "", "| " + " | ".join(t["columns"]) + " |", "|" + "---|" * len(t["columns"])]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in t["rows"]]
    return lines + [""]


def render(report: dict, out: Path) -> str:
    lines = [f"# rg report: {report['scene']}", "", f"Machine: {report['machine']}. Budgets: {report['budgets_name']}. "
             f"Total {report['seconds']:.0f} s.", "", "## Recommended settings", ""]
    lines += [f"- {r}" for r in report["recommendations"]] + [""]
    for name, sec in report["sections"].items():
        lines += [f"## {TITLES[name]}", ""]
        if "error" in sec:
            lines += [f"**This section failed** after {sec['seconds']:.1f} s: `{sec['error']}`", ""]
            continue
        lines += sec.get("text", []) + [""]
        for t in sec.get("tables", []):
            lines += table(t)
        for p in sec.get("plots", []):
            rel = Path(p).resolve().relative_to(out.resolve())
            lines += [f"![{TITLES[name]}]({rel.as_posix()})", ""]
        lines += [f"_{sec['seconds']:.1f} s_", ""]
    return "\n".join(lines)
