"""The open-vocabulary segmentation benchmarks scored as they define it, on scenes that hold their
labels (io/ovs_labels.py). LERF-OVS has two protocols whose figures differ by tens of points
(LangSplat 51.4 against 9.66 under OpenGaussian's), so both are reported, labelled apart:

- `2d_relevancy`, LangSplat's scorer: per labelled view and category the relevancy of the category's
  text is rendered at each level, smoothed to (r + mean_30x30(r)) / 2, the level whose smoothed map
  peaks highest kept, min-max normalised, stretched to [-1, 1] and clipped at 0, thresholded at 0.4
  and cleaned by a 7x7 majority vote: IoU with the category's mask, mIoU over (view, category).
  Localization: the peak of the 30x30 mean-filtered relevancy (level by its peak) falls inside one
  of the category's boxes. LangSplat's three SAM levels are here the median physical scales of the
  map's part, object and group masks (the field's scale is continuous).
- `3d_selection`, OpenGaussian's: the Gaussians the project's grounding selects for the category,
  rendered alone in the view (the amodal mask `rg eval` scores), IoU with the mask; also the visible
  mask (the group's share of the full render).

3D-OVS: every pixel takes the class of highest relevancy (each class at its level), IoU per class
and view with scikit-learn's convention of its released scorer (an empty union counts 0), mIoU
over (view, class), and pixel accuracy; its 3D selection: each class's grounded group, as above.
The windows (30 px, 7x7) are LangSplat's at the labels' resolution, scaled to the rendered one.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import cv2
import numpy as np

from .grounding import iou

LEVEL_NAMES = ("part", "object", "group")   # KeyframeSupervision.levels 0, 1, 2


@dataclass(frozen=True)
class LangSplatRule:
    """LangSplat's LERF-OVS rule: mean filter size, threshold and majority-vote radius (pixels)."""

    kernel: int = 30
    threshold: float = 0.4
    vote: int = 3

    def scaled(self, s: float) -> "LangSplatRule":
        """The same rule on images `s` times the labels' width."""
        return LangSplatRule(max(1, round(self.kernel * s)), self.threshold, max(0, round(self.vote * s)))


def mean_filter(x: np.ndarray, k: int) -> np.ndarray:
    """k x k mean [H, W] float64 (window offsets -k//2 .. k - k//2 - 1, borders mirrored without
    repeating the edge: OpenCV's filter2D defaults, as LangSplat's scorer ran it)."""
    return cv2.blur(np.asarray(x, np.float64), (k, k), borderType=cv2.BORDER_REFLECT_101)


def majority_vote(mask: np.ndarray, r: int) -> np.ndarray:
    """bool [H, W]: a pixel is set when more than half of its (2r+1)^2 window (cut at the image
    border) is set; a tie clears it."""
    if r <= 0:
        return np.asarray(mask, bool)
    k = (2 * r + 1, 2 * r + 1)
    m = np.asarray(mask, np.float64)
    ones = cv2.boxFilter(m, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    n = cv2.boxFilter(np.ones_like(m), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    return 2 * ones > n + 0.5


def langsplat_mask(levels: np.ndarray, rule: LangSplatRule = LangSplatRule()) -> tuple[np.ndarray, int]:
    """Relevancy at each level [L, H, W] -> (the predicted mask bool [H, W], the level kept)."""
    smooth = [0.5 * (r + mean_filter(r, rule.kernel)) for r in np.asarray(levels, np.float64)]
    lvl = int(np.argmax([s.max() for s in smooth]))
    s = smooth[lvl]
    n = (s - s.min()) / (s.max() - s.min() + 1e-9)
    return majority_vote(np.clip(2.0 * n - 1.0, 0.0, 1.0) > rule.threshold, rule.vote), lvl


def langsplat_localized(levels: np.ndarray, boxes: np.ndarray, rule: LangSplatRule = LangSplatRule()) -> tuple[bool, int]:
    """Relevancy [L, H, W], boxes [K, 4] x1 y1 x2 y2 -> (a peak of the mean-filtered relevancy at
    the level that peaks highest lies in a box (edges included), that level)."""
    filt = [mean_filter(r, rule.kernel) for r in np.asarray(levels, np.float64)]
    lvl = int(np.argmax([f.max() for f in filt]))
    ys, xs = np.nonzero(filt[lvl] == filt[lvl].max())
    for x1, y1, x2, y2 in np.asarray(boxes, np.float64).reshape(-1, 4):
        inside = (xs >= min(x1, x2)) & (xs <= max(x1, x2)) & (ys >= min(y1, y2)) & (ys <= max(y1, y2))
        if inside.any():
            return True, lvl
    return False, lvl


def argmax_segmentation(scores: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, float]:
    """Class scores [C, H, W] and ground-truth masks [C, H, W] -> (IoU per class [C] of the per-pixel
    argmax, an empty union counting 0; pixel accuracy: share of pixels whose one-hot class row equals
    the ground truth's)."""
    C = len(scores)
    pred = np.asarray(scores).argmax(0)[None] == np.arange(C)[:, None, None]   # [C, H, W]
    gt = np.asarray(gt, bool)
    inter, union = (pred & gt).sum((1, 2)), (pred | gt).sum((1, 2))
    ious = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
    return ious, float((pred == gt).all(0).mean())


def map_levels(grounder) -> list[tuple[str, float]]:
    """(name, scale in m) of the levels the 2D protocol renders: per mask level of the map's
    supervision (part, object, group) the median scale of its masks."""
    sup = getattr(grounder.mapper, "supervision", None)
    if sup is None or not sup.by_keyframe:
        raise ValueError("benchmark scoring needs a map with 2D supervision (its mask scales are the levels)")
    lv = np.concatenate([s.levels for s in sup.by_keyframe.values()])
    sc = np.concatenate([s.scales for s in sup.by_keyframe.values()])
    out = [(name, float(np.median(sc[lv == i]))) for i, name in enumerate(LEVEL_NAMES) if (lv == i).any()]
    return out or [("all", float(np.median(sc)))]


def _relevancy_levels(grounder, text, levels, f, fr) -> np.ndarray:   # [L, H, W]
    """The text's relevancy at each level in view f (field render fr). Where the map renders
    nothing (LangSplat's maps cover the whole image) it takes the lowest rendered value, so the
    min-max normalisation spans the rendered relevancy as it does there."""
    W, H = f.intrinsics.width, f.intrinsics.height
    rel = np.stack([grounder.relevancy_view(text, s, f.intrinsics.K, f.cam_to_world, W, H, render=fr)[0].numpy()
                    for _, s in levels]).astype(np.float64)
    covered = fr.alpha.numpy() > grounder.gcfg.mask_alpha                  # [H, W]
    if covered.any() and not covered.all():
        rel[:, ~covered] = rel[:, covered].min(1)[:, None]
    return rel


def _selection(grounder, answers: dict, text: str, f) -> tuple[float, float, object]:
    """The category's answer (asked once) -> its amodal and visible masks in view f."""
    if text not in answers:
        answers[text] = grounder.ground(text, mode="explicit")
    res = answers[text]
    amodal, visible, _ = grounder.mask_layers(res, f.intrinsics.K, f.cam_to_world, f.intrinsics.width, f.intrinsics.height)
    return amodal, visible, res


def _pct(v) -> float:
    return round(100.0 * float(np.mean(v)), 2) if len(v) else float("nan")


PROTOCOL_2D = ("LangSplat: rendered relevancy at the level whose smoothed map peaks highest, (r + mean_30(r)) / 2, "
               "min-max normalised, > 0.4 once stretched to [-1, 1], 7x7 majority vote; localization: the "
               "mean_30 peak inside a box")
PROTOCOL_3D = "OpenGaussian: the Gaussians selected in 3D (the grounded group) rendered alone in the view"


def evaluate_lerf_ovs(grounder, scene, rule: LangSplatRule = LangSplatRule(), progress: bool = False) -> dict:
    """Both LERF-OVS protocols over the scene's labelled views (scene.labels, benchmark lerf_ovs)."""
    from tqdm import tqdm

    t0, levels, answers, rows, empty = time.perf_counter(), map_levels(grounder), {}, [], 0
    for view in tqdm(scene.labels.views, desc="lerf_ovs", unit="view", disable=not progress, file=sys.stderr):
        f = view.frame
        r = rule.scaled(f.intrinsics.width / view.size[0])
        fr = grounder.field.render(f.intrinsics.K, f.cam_to_world, f.intrinsics.width, f.intrinsics.height)
        boxes = view.frame_boxes()
        for cat, gt in view.masks().items():
            if not gt.any():   # the labelled region left the undistorted image
                empty += 1
                continue
            rel = _relevancy_levels(grounder, cat, levels, f, fr)
            mask, lvl = langsplat_mask(rel, r)
            loc, _ = langsplat_localized(rel, boxes[cat], r)
            amodal, visible, res = _selection(grounder, answers, cat, f)
            rows.append({"view": f.index, "category": cat, "iou_2d": iou(mask, gt), "localized": loc,
                         "level": levels[lvl][0], "iou_3d": iou(amodal, gt), "iou_3d_visible": iou(visible, gt),
                         "target": res.target, "success": bool(res.success)})
    per_cat = {}
    for c in dict.fromkeys(r["category"] for r in rows):
        rs = [r for r in rows if r["category"] == c]
        per_cat[c] = {"pairs": len(rs), "iou_2d": _pct([r["iou_2d"] for r in rs]),
                      "localization": _pct([r["localized"] for r in rs]), "iou_3d": _pct([r["iou_3d"] for r in rs])}
    return {"views": len(scene.labels.views), "categories": len(per_cat), "pairs": len(rows), "empty_masks": empty,
            "levels_m": {n: round(s, 4) for n, s in levels},
            "2d_relevancy": {"protocol": PROTOCOL_2D, "miou": _pct([r["iou_2d"] for r in rows]),
                             "localization": _pct([r["localized"] for r in rows]),
                             "levels_kept": {n: sum(r["level"] == n for r in rows) for n, _ in levels}},
            "3d_selection": {"protocol": PROTOCOL_3D, "miou": _pct([r["iou_3d"] for r in rows]),
                             "miou_visible": _pct([r["iou_3d_visible"] for r in rows]),
                             "success_rate": _pct([r["success"] for r in rows])},
            "per_category": per_cat, "seconds": round(time.perf_counter() - t0, 3)}


def evaluate_3d_ovs(grounder, scene, rule: LangSplatRule = LangSplatRule(), progress: bool = False) -> dict:
    """3D-OVS mIoU over its classes (scene.labels, benchmark 3d_ovs): per-pixel argmax of the
    relevancy, and each class's 3D selection."""
    from tqdm import tqdm

    t0, levels, classes, answers = time.perf_counter(), map_levels(grounder), scene.labels.classes, {}
    ious_2d, accs, ious_3d, ious_3d_vis = [], [], [], []
    for view in tqdm(scene.labels.views, desc="3d_ovs", unit="view", disable=not progress, file=sys.stderr):
        f = view.frame
        r = rule.scaled(f.intrinsics.width / view.size[0])
        fr = grounder.field.render(f.intrinsics.K, f.cam_to_world, f.intrinsics.width, f.intrinsics.height)
        masks = view.masks()
        gt = np.stack([masks[c] for c in classes])                         # [C, H, W]
        scores = []
        for c in classes:
            rel = _relevancy_levels(grounder, c, levels, f, fr)
            scores.append(rel[langsplat_mask(rel, r)[1]])
        ious, acc = argmax_segmentation(np.stack(scores), gt)
        ious_2d.append(ious)
        accs.append(acc)
        sel = [_selection(grounder, answers, c, f) for c in classes]
        ious_3d.append([iou(a, g) for (a, _, _), g in zip(sel, gt)])
        ious_3d_vis.append([iou(v, g) for (_, v, _), g in zip(sel, gt)])
    i2d = np.array(ious_2d).reshape(-1, len(classes))
    return {"views": len(scene.labels.views), "classes": classes,
            "levels_m": {n: round(s, 4) for n, s in levels},
            "2d_relevancy": {"protocol": "3D-OVS: every pixel the class of highest relevancy (each class at its "
                                         "level), IoU per class and view (empty union 0)",
                             "miou": _pct(i2d), "accuracy": _pct(accs)},
            "3d_selection": {"protocol": PROTOCOL_3D, "miou": _pct(ious_3d), "miou_visible": _pct(ious_3d_vis)},
            "per_class_iou_2d": {c: _pct(i2d[:, k]) for k, c in enumerate(classes)},
            "seconds": round(time.perf_counter() - t0, 3)}


def evaluate_labels(grounder, scene, progress: bool = False) -> dict:
    """{benchmark: figures} for the labels a scene holds ({} without any)."""
    labels = getattr(scene, "labels", None)
    if labels is None:
        return {}
    if labels.benchmark == "lerf_ovs":
        return {"lerf_ovs": evaluate_lerf_ovs(grounder, scene, progress=progress)}
    if labels.benchmark == "3d_ovs":
        return {"3d_ovs": evaluate_3d_ovs(grounder, scene, progress=progress)}
    raise ValueError(f"unknown benchmark labels {labels.benchmark!r} (lerf_ovs or 3d_ovs)")
