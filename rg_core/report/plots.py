"""PNG line plots (matplotlib, Agg): each curve marks the default budget or the stop test's point with
a ring and a label; log axes label 1-2-5 steps as plain numbers."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _save(fig, path, title: str = "") -> str:
    """Title, lay out, write (creating the folder) and close a figure; returns the path."""
    import matplotlib.pyplot as plt

    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)


def line_plot(path: Path, panels: list[dict], title: str = "") -> str:
    """panels: [{"x": label, "y": label, "series": [(name, xs, ys)], "mark": [(x, y, text)],
    "logx": bool, "logy": bool}] side by side. Returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 3.5), squeeze=False)
    for ax, p in zip(axes[0], panels):
        for name, xs, ys in p["series"]:
            ax.plot(xs, ys, "o-", label=name, ms=4)
        for x, y, text in p.get("mark", []):
            ax.plot([x], [y], "o", ms=11, mfc="none", mec="red", mew=1.5)
            ax.annotate(text, (x, y), textcoords="offset points", xytext=(6, 6), fontsize=7, color="red")
        for axis, on in ((ax.xaxis, p.get("logx")), (ax.yaxis, p.get("logy"))):
            if on:  # plain-number labels at 1-2-5 steps, none on the minor ticks (they overlapped)
                (ax.set_xscale if axis is ax.xaxis else ax.set_yscale)("log")
                axis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
                axis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
                axis.set_minor_formatter(ticker.NullFormatter())
        ax.set_xlabel(p["x"])
        ax.set_ylabel(p["y"])
        ax.grid(alpha=0.3)
        if len(p["series"]) > 1:
            ax.legend(fontsize=7)
    return _save(fig, path, title)


def photo_psnr_png(curve: list, path, stopped: str = "", title: str = "") -> str:
    """Held-out PSNR (dB) against seconds of a photo-only fit (photo_fit.fit_summary's heldout_psnr
    rows [step, seconds, PSNR, Gaussians]), the last point ringed with why it stopped; Gaussians on
    the second panel."""
    if not curve:
        raise ValueError("photo fit: no held-out PSNR measured (fewer than 3 views, photo.holdout_views 0, "
                         "or check_every larger than the steps run)")
    steps, secs, psnr, n = (list(c) for c in zip(*curve))
    last = f"step {steps[-1]}" + (f", {stopped}" if stopped else "")
    return line_plot(path, [
        {"x": "fit seconds", "y": "held-out PSNR (dB)", "series": [("held-out views", secs, psnr)],
         "mark": [(secs[-1], psnr[-1], last)]},
        {"x": "fit seconds", "y": "Gaussians", "series": [("Gaussians", secs, n)]}], title)


def calibration_png(queries: list[dict], path, threshold: float | None = None, title: str = "") -> str:
    """Risk against coverage (answers sorted by confidence, the threshold's point ringed) and the
    reliability diagram (share right against mean confidence, 10 bins) of one run's queries."""
    from ..eval.grounding import risk_coverage

    p = np.array([q["confidence"] for q in queries], np.float64)
    y = np.array([q["right"] for q in queries], bool)
    rc = risk_coverage(p, y)
    mark = []
    if threshold is not None and len(p):
        n = int((p >= threshold).sum())
        if n:
            mark.append((n / len(p), float((~y[p >= threshold]).mean()), f"threshold {threshold:.2f}"))
    b = np.minimum((p * 10).astype(np.int64), 9)
    bins = [i for i in range(10) if (b == i).any()]
    panels = [{"x": "coverage (share of answers returned)", "y": "risk (share of returned that are wrong)",
               "series": [("all answers", rc.get("coverage", []), rc.get("risk", []))], "mark": mark},
              {"x": "mean confidence", "y": "share right", "series": [
                  ("answers", [float(p[b == i].mean()) for i in bins], [float(y[b == i].mean()) for i in bins]),
                  ("calibrated", [0.0, 1.0], [0.0, 1.0])]}]
    return line_plot(path, panels, title)


def scenes_png(per_scene: dict[str, list], seconds: list, path, title: str = "") -> str:
    """The per-scene distribution of a many-scene `rg eval`: each kind's scene mIoU as a box with every
    scene a dot (its median and quartiles at a glance, outliers by name in the JSON), and the seconds
    each scene took."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = [k for k, v in per_scene.items() if len(v)]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(9.2, 3.6), gridspec_kw={"width_ratios": [max(2, len(kinds)), 2]})
    if kinds:
        data = [np.asarray(per_scene[k], np.float64) for k in kinds]
        ax.boxplot(data, showfliers=False)
        ax.set_xticks(range(1, len(kinds) + 1), kinds)
        rng = np.random.default_rng(0)   # the dots' horizontal jitter: the same picture every time
        for i, d in enumerate(data, 1):
            ax.plot(i + rng.uniform(-0.12, 0.12, len(d)), d, "o", ms=3, alpha=0.5)
    ax.set_ylabel("visible mIoU per scene (%)")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    s = np.asarray(seconds, np.float64)
    bx.hist(s, bins=min(30, max(5, len(s) // 3 or 1)))
    bx.set_xlabel("seconds per scene")
    bx.set_ylabel("scenes")
    bx.grid(alpha=0.3)
    return _save(fig, path, title)
