"""Contact sheet of a scene: for a few views, RGB, depth, visible instances and amodal masks."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.scene import Scene


def _label_colors(n: int) -> np.ndarray:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    cols = np.array([cmap(i % 10)[:3] for i in range(max(n, 1))])
    return np.concatenate([[[0.0, 0.0, 0.0]], cols])  # id 0 = background, black


def write_contact_sheet(scene: Scene, out_png: str | Path, max_views: int = 4) -> Path:
    """One row per view: RGB | depth (m) | visible ids | amodal outlines over RGB."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = scene.frames
    if not frames:
        raise ValueError(f"{scene.root}: scene has no frames to show")
    pick = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, min(max_views, len(frames)))]
    ids = [o.id for o in scene.objects]
    names = {o.id: o.name for o in scene.objects}
    colors = _label_colors(max(ids, default=0))
    has_masks = pick[0].visible_mask_path is not None
    ncol = 4 if has_masks else 2
    fig, axes = plt.subplots(len(pick), ncol, figsize=(3.2 * ncol, 2.5 * len(pick)), squeeze=False)
    for r, fr in enumerate(pick):
        rgb = fr.load_rgb()
        depth = fr.load_depth()
        axes[r, 0].imshow(rgb)
        axes[r, 0].set_title(f"view {fr.index:04d}", fontsize=8)
        d = np.where(depth > 0, depth, np.nan)
        lo, hi = (np.nanpercentile(d, [1, 95]) if np.isfinite(d).any() else (0.0, 1.0))
        im = axes[r, 1].imshow(d, cmap="viridis", vmin=lo, vmax=hi)
        axes[r, 1].set_title("depth (m), blank = invalid", fontsize=8)
        fig.colorbar(im, ax=axes[r, 1], fraction=0.046, pad=0.02)
        if has_masks:
            vis = fr.load_visible_mask()
            axes[r, 2].imshow(colors[np.clip(vis, 0, len(colors) - 1)])
            axes[r, 2].set_title("visible instances", fontsize=8)
            grey = rgb.astype(np.float64).mean(-1, keepdims=True) / 255.0
            over = np.repeat(0.35 + 0.4 * grey, 3, axis=-1)
            for oid in ids:
                am = fr.load_complete_mask(oid)
                occluded = am & (vis != oid)
                over[am & ~occluded] = 0.6 * over[am & ~occluded] + 0.4 * colors[oid]
                over[occluded] = colors[oid]
                if am.any():
                    axes[r, 3].contour(am, levels=[0.5], colors=[colors[oid]], linewidths=0.6)
            axes[r, 3].imshow(over)
            axes[r, 3].set_title("amodal masks (solid = occluded part)", fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    if names:
        legend = ", ".join(f"{i}: {n}" for i, n in sorted(names.items()))
        fig.suptitle(f"{Path(scene.root).name}  |  {legend}", fontsize=8)
    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png
