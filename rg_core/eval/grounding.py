"""Grounding quality on a scene's test views (`rg eval`): visible and amodal mask mIoU, LERF
localization accuracy, 3D box IoU and seconds per query and stage, for explicit and implicit
queries (and relational ones generated from the ground truth, when asked); and the paper's ablation
(relevancy only / + reasoning / + hierarchical grouping)."""
from __future__ import annotations

import sys
import time

import numpy as np

from ..geometry.conventions import project
from ..grounding.boxes import box_iou_aabb
from ..io.scene import depth_or_none


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = int((a | b).sum())
    return float((a & b).sum()) / u if u else 1.0


def _box2d_contains(mask: np.ndarray, x: int, y: int) -> bool:
    ys, xs = np.nonzero(mask)
    return bool(len(ys)) and xs.min() <= x <= xs.max() and ys.min() <= y <= ys.max()


def evaluate_queries(grounder, scene, implicit_per_object: int = 1, min_visible_px: int = 20,
                     views: list | None = None, progress: bool = False, ablation: bool = False,
                     relational: int = 0) -> dict:
    """Every explicit query and the first `implicit_per_object` implicit ones of queries.json, on
    every test view where the object is visible (>= min_visible_px pixels). Masks, boxes and
    localization are those of the answer's groups, an abstained answer's best guess too (the
    figures stay comparable across thresholds); abstention shows in success_rate and "confidence".
    A query asked of several objects (two objects named "remote control") is asked once and scored
    against the one of them the answer's box overlaps most: either is a right answer to the name.
    `relational` > 0: that many relational queries from the ground truth (eval/relational.py), asked
    from the first test camera and scored against the object they expect (kind "relational"; its
    localization: the answer's box centre falls inside the object's 2D box, since the answer comes
    from the scene graph, not from a relevancy peak)."""
    from tqdm import tqdm

    by_id = {o.id: o for o in scene.objects}
    views = scene.test if views is None else views
    cache = [(f, f.load_visible_mask(), d, None if d is None else f.load_rgb())   # RGB-D views: masks follow both
             for f, d in ((f, depth_or_none(f)) for f in views)]
    jobs: dict[tuple[str, str], list[int]] = {}   # (kind, text) -> the objects it is asked of
    for q in scene.queries:
        if q.object_id in by_id:
            jobs.setdefault(("explicit", q.explicit), []).append(q.object_id)
            for t in q.implicit[:implicit_per_object]:
                jobs.setdefault(("implicit", t), []).append(q.object_id)
    rel_cam = None
    if relational > 0:
        from .relational import scored_queries

        rel_cam = scene.test[0].cam_to_world if scene.test else None
        for q in scored_queries(scene, relational):
            jobs.setdefault(("relational", q["text"]), []).extend(o.id for o in scene.objects if o.name == q["expect"])
    rows, abl = [], []
    for (kind, text), oids in tqdm(list(jobs.items()), desc="eval", unit="query", disable=not progress, file=sys.stderr):
        t0 = time.perf_counter()
        res = (grounder.ground(text, cam_to_world=rel_cam) if kind == "relational" else grounder.ground(text, mode=kind))
        t_query = time.perf_counter() - t0
        o, box = by_id[oids[0]], 0.0
        if res.objects:   # an abstained answer is scored by its best guess: the figures stay comparable
            ob = res.objects[0]
            box, o = max(((box_iou_aabb(ob.aabb_min, ob.aabb_max, by_id[i].aabb_min, by_id[i].aabb_max), by_id[i])
                          for i in dict.fromkeys(oids)), key=lambda x: x[0])
        oid = o.id
        right_name = res.target == o.name
        for f, vis_ids, depth, rgb in cache:
            gt_vis = vis_ids == oid
            if gt_vis.sum() < min_visible_px:
                continue
            gt_amodal = f.load_complete_mask(oid) if f.has_amodal_masks() else None   # None: not in the data
            W, H = f.intrinsics.width, f.intrinsics.height
            t1 = time.perf_counter()
            amodal, visible, visible_d = grounder.mask_layers(res, f.intrinsics.K, f.cam_to_world, W, H, depth, rgb)
            t_mask = time.perf_counter() - t1
            loc = False
            if res.objects and kind == "relational":
                c = (np.asarray(res.objects[0].aabb_min) + np.asarray(res.objects[0].aabb_max)) / 2
                uv, z = project(c[None], f.intrinsics.K, f.cam_to_world)
                loc = bool(z[0] > 0) and _box2d_contains(gt_vis, int(round(uv[0, 0])), int(round(uv[0, 1])))
            elif res.objects:
                rel, _ = grounder.relevancy_view(res.target, res.scale, f.intrinsics.K, f.cam_to_world, W, H)
                y, x = divmod(int(rel.reshape(-1).argmax()), W)
                loc = _box2d_contains(gt_vis, x, y)
            rows.append({"kind": kind, "query": text, "object": o.name, "view": f.index, "success": res.success,
                         "asked_of": len(oids),
                         "target": res.target, "confidence": float(res.confidence), "evidence": res.evidence,
                         "target_ok": right_name, "iou_visible": iou(visible, gt_vis),
                         "iou_visible_depth": None if visible_d is None else iou(visible_d, gt_vis),
                         "iou_amodal": None if gt_amodal is None else iou(amodal, gt_amodal), "localized": loc, "box_iou": box,
                         "seconds_query": t_query, "seconds_masks": t_mask, "timings": res.timings})
            if ablation and gt_amodal is not None and kind != "relational":
                abl.append(_ablation_row(grounder, kind, text, o, f, gt_vis, gt_amodal, amodal))
    out = summarise(rows)
    if ablation:
        out["ablation"] = _summarise_ablation(abl)
    return out


def _ablation_row(grounder, kind, text, o, f, gt_vis, gt_amodal, amodal_full) -> dict:
    """Relevancy-only (LangSplat-style: pixels with relevancy > 0.5 for the raw query text),
    + reasoning (the same with the reasoner's target), + grouping (the full pipeline, amodal)."""
    W, H = f.intrinsics.width, f.intrinsics.height
    K, c2w = f.intrinsics.K, f.cam_to_world
    sup = grounder.mapper.supervision
    scale = float(np.median(np.concatenate([s.scales for s in sup.by_keyframe.values()])))
    t0 = time.perf_counter()
    rel_q, _ = grounder.relevancy_view(text, scale, K, c2w, W, H)
    t1 = time.perf_counter()
    target = grounder.reasoner.reason(text, grounder.vocabulary(), mode=kind).target or text
    rel_t, _ = grounder.relevancy_view(target, scale, K, c2w, W, H)
    t2 = time.perf_counter()
    return {"kind": kind, "relevancy_only": iou(rel_q.numpy() > 0.5, gt_vis),
            "with_reasoning": iou(rel_t.numpy() > 0.5, gt_vis),
            "with_grouping_amodal": iou(amodal_full, gt_amodal),
            "seconds": {"relevancy_only": t1 - t0, "with_reasoning": t2 - t1}}


def _summarise_ablation(rows: list[dict]) -> dict:
    out = {}
    for col in ("relevancy_only", "with_reasoning", "with_grouping_amodal"):
        out[col] = {"miou": round(100 * float(np.mean([r[col] for r in rows])), 2) if rows else float("nan")}
    for col in ("relevancy_only", "with_reasoning"):
        out[col]["seconds_per_view"] = round(float(np.mean([r["seconds"][col] for r in rows])), 4) if rows else 0.0
    return out


KINDS = ("explicit", "implicit", "relational")


def kinds_of(rows: list[dict]) -> tuple[str, ...]:
    """explicit and implicit always (as rg eval has always reported them), relational when asked."""
    return tuple(k for k in KINDS if k != "relational" or any(r["kind"] == k for r in rows))


def summarise(rows: list[dict]) -> dict:
    def block(rs):
        if not rs:
            return {"pairs": 0}
        m = lambda k: float(np.mean([r[k] for r in rs]))
        return {"pairs": len(rs), "queries": len({r["query"] for r in rs}),
                "miou_visible": round(100 * m("iou_visible"), 2), "miou_visible_depth": _with_depth(rs),
                "miou_amodal": _amodal(rs),
                "localization": round(100 * m("localized"), 2), "target_accuracy": round(100 * m("target_ok"), 2),
                "success_rate": round(100 * m("success"), 2)}

    out = {k: block([r for r in rows if r["kind"] == k]) for k in kinds_of(rows)}
    out["all"] = block(rows)
    out["queries_asked_of_several"] = len({r["query"] for r in rows if r.get("asked_of", 1) > 1})
    per_obj: dict[str, float] = {}
    for r in rows:
        if r["kind"] == "explicit":
            per_obj[r["object"]] = r["box_iou"]
    per_obj_masks: dict[str, list] = {}
    for r in rows:
        per_obj_masks.setdefault(r["object"], []).append(r)
    def obj_block(rs):
        m = lambda k: round(100 * float(np.mean([r[k] for r in rs])), 2)
        return {"pairs": len(rs), "miou_visible": m("iou_visible"), "miou_visible_depth": _with_depth(rs),
                "miou_amodal": _amodal(rs),
                "localization": m("localized"), "target_accuracy": m("target_ok")}

    # Per object over both kinds, and per kind: an implicit query the reasoner maps to another name
    # scores 0 whatever the 3D part does (with oracle supervision the explicit figures are the 3D part's).
    out["per_object"] = {}
    for k, rs in per_obj_masks.items():
        out["per_object"][k] = obj_block(rs)
        for kind in kinds_of(rows):
            sub = [r for r in rs if r["kind"] == kind]
            if sub:
                out["per_object"][k][kind] = obj_block(sub)
    out["box_iou"] = {"per_object": {k: round(v, 3) for k, v in per_obj.items()},
                      "share_at_0.5": round(float(np.mean([v >= 0.5 for v in per_obj.values()])), 3) if per_obj else 0.0}
    q = {}
    for r in rows:
        q.setdefault(r["query"], r)
    stages: dict[str, list] = {}
    for r in q.values():
        for k, v in r["timings"].items():
            stages.setdefault(k, []).append(v)
    out["queries"] = per_query(rows)
    out["confidence"] = calibration(out["queries"])
    out["seconds"] = {"per_query_median": round(float(np.median([r["seconds_query"] for r in q.values()])), 4) if q else 0.0,
                      "masks_per_view_median": round(float(np.median([r["seconds_masks"] for r in rows])), 4) if rows else 0.0,
                      "stages_median": {k: round(float(np.median(v)), 4) for k, v in stages.items()}}
    return out


def _with_depth(rows: list[dict]) -> float:
    """Visible mIoU (%) with masks sharpened by each test view's own depth and colour images (what the
    node does with its current frame); nan when no view has depth."""
    v = [r["iou_visible_depth"] for r in rows if r.get("iou_visible_depth") is not None]
    return round(100 * float(np.mean(v)), 2) if v else float("nan")


def _amodal(rows: list[dict]) -> float:
    """Amodal mIoU (%) over the rows whose scene has amodal masks; nan when none has (YCB-Video)."""
    v = [r["iou_amodal"] for r in rows if r["iou_amodal"] is not None]
    return round(100 * float(np.mean(v)), 2) if v else float("nan")


RIGHT_IOU = 0.5   # an answer is right when its target is the object and its visible masks reach this mean IoU


def per_query(rows: list[dict]) -> list[dict]:
    """One record per (kind, query): the answer, its confidence and evidence, and whether it is right
    (target right and mean visible IoU over the test views >= RIGHT_IOU)."""
    by: dict[tuple, list[dict]] = {}
    for r in rows:
        by.setdefault((r["kind"], r["query"], r["object"]), []).append(r)
    out = []
    for (kind, query, obj), rs in by.items():
        miou = float(np.mean([r["iou_visible"] for r in rs]))
        r0 = rs[0]
        out.append({"kind": kind, "query": query, "object": obj, "target": r0.get("target", ""),
                    "success": bool(r0["success"]), "answered": bool(r0.get("evidence")),
                    "confidence": round(float(r0.get("confidence", 0.0)), 4), "miou_visible": round(100 * miou, 2),
                    "box_iou": round(float(r0["box_iou"]), 3),
                    "right": bool(r0["target_ok"] and miou >= RIGHT_IOU),
                    "evidence": {k: round(float(v), 4) for k, v in (r0.get("evidence") or {}).items()}})
    return out


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve of `scores` for labels True against False (ties count half); nan
    when one class is missing."""
    s, y = np.asarray(scores, np.float64), np.asarray(labels, bool)
    pos, neg = s[y], s[~y]
    if not len(pos) or not len(neg):
        return float("nan")
    from scipy.stats import rankdata

    ranks = rankdata(np.concatenate([pos, neg]))
    return float((ranks[:len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def expected_calibration_error(p: np.ndarray, y: np.ndarray, bins: int = 10) -> float:
    """sum over equal-width probability bins of (share of answers) * |mean p - share right|."""
    p, y = np.asarray(p, np.float64), np.asarray(y, np.float64)
    if not len(p):
        return float("nan")
    b = np.minimum((p * bins).astype(np.int64), bins - 1)
    return float(sum(abs(p[b == i].mean() - y[b == i].mean()) * (b == i).mean() for i in range(bins) if (b == i).any()))


def risk_coverage(p: np.ndarray, y: np.ndarray) -> dict:
    """Answers sorted by confidence, most sure first: coverage (share answered) and risk (share of
    the answered that are wrong) after each one."""
    order = np.argsort(-np.asarray(p, np.float64), kind="stable")
    wrong = np.cumsum(~np.asarray(y, bool)[order])
    n = np.arange(1, len(order) + 1)
    return {"coverage": (n / max(len(order), 1)).round(4).tolist(), "risk": (wrong / n).round(4).tolist(),
            "confidence": np.asarray(p, np.float64)[order].round(4).tolist()}


def calibration(queries: list[dict]) -> dict:
    """How well confidence separates right from wrong answers over one run's queries: AUROC, ECE,
    and at the run's abstention decisions the share of all answers that are wrong yet returned as
    success and the share of right answers still returned. Per kind and over all."""
    def block(qs):
        if not qs:
            return {"answers": 0}
        p = np.array([q["confidence"] for q in qs])
        y = np.array([q["right"] for q in qs])
        ok = np.array([q["success"] for q in qs])
        return {"answers": len(qs), "right": int(y.sum()), "auroc": round(auroc(p, y), 4),
                "ece": round(expected_calibration_error(p, y), 4),
                "wrong_success_share": round(float((ok & ~y).mean()), 4),
                "right_returned_share": round(float(ok[y].mean()), 4) if y.any() else float("nan"),
                "abstained": int((~ok).sum())}

    out = {k: block([q for q in queries if q["kind"] == k]) for k in kinds_of(queries)}
    out["all"] = block(queries)
    out["risk_coverage"] = risk_coverage(np.array([q["confidence"] for q in queries]),
                                         np.array([q["right"] for q in queries], bool)) if queries else {}
    return out

