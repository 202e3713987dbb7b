"""Pictures of one grounding answer: the rendered view, relevancy, amodal and visible masks (PNG)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def mask_summary(amodal: np.ndarray, visible: np.ndarray, depth: np.ndarray | None,
                 image: np.ndarray | None = None) -> dict:
    """What `rg ground` and `rg demo` report of an answer's masks [H, W]: size, pixels, and whether the
    visible mask followed a depth image and a colour image (else it is the render's alone)."""
    h, w = visible.shape
    return {"width": w, "height": h, "amodal_pixels": int(amodal.sum()), "visible_pixels": int(visible.sum()),
            "visible_follows_depth": depth is not None, "visible_follows_image": image is not None}


def write_grounding_pngs(grounder, result, K, c2w, width: int, height: int, amodal: np.ndarray,
                         visible: np.ndarray, out: Path) -> dict:
    """One figure (render | relevancy | amodal | visible) plus the masks as separate PNGs."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    rel, fr = grounder.relevancy_view(result.target, result.scale, K, c2w, width, height)
    rgb = fr.rgb.clamp(0, 1).numpy()
    paths = {"amodal": out / "amodal_mask.png", "visible": out / "visible_mask.png", "figure": out / "grounding.png"}
    cv2.imwrite(str(paths["amodal"]), amodal.astype(np.uint8) * 255)
    cv2.imwrite(str(paths["visible"]), visible.astype(np.uint8) * 255)
    fig, ax = plt.subplots(1, 4, figsize=(16, 3.6))
    ax[0].imshow(rgb)
    ax[0].set_title("render")
    r = rel.numpy()
    cov = r[fr.alpha.numpy() > 0.5]
    lo, hi = (np.percentile(cov, [1, 99.5]) if cov.size else (0.0, 1.0))
    im = ax[1].imshow(r, cmap="turbo", vmin=float(lo), vmax=float(max(hi, lo + 1e-3)))  # stretched: values sit near 0.5
    ax[1].set_title(f"relevancy: {result.target}")
    fig.colorbar(im, ax=ax[1], fraction=0.046)
    for a, m, name, col in ((ax[2], amodal, "amodal", (1.0, 0.2, 0.2)), (ax[3], visible, "visible", (0.2, 1.0, 0.2))):
        over = rgb.copy()
        over[m] = 0.5 * over[m] + 0.5 * np.array(col)
        a.imshow(over)
        a.set_title(f"{name} mask ({int(m.sum())} px)")
    for a in ax:
        a.axis("off")
    fig.suptitle(f"{result.query!r} -> {result.target} (confidence {result.confidence:.2f})", fontsize=10)
    fig.tight_layout()
    fig.savefig(paths["figure"], dpi=90)
    plt.close(fig)
    return {k: str(v) for k, v in paths.items()}
