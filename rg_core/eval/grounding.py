"""Grounding quality on a scene's test views (`rg eval`): visible and amodal mask mIoU, LERF
localization accuracy, 3D box IoU and seconds per query and stage, for explicit and implicit
queries; and the paper's ablation (relevancy only / + reasoning / + hierarchical grouping)."""
from __future__ import annotations

import sys
import time

import numpy as np

from ..grounding.boxes import box_iou_aabb


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = int((a | b).sum())
    return float((a & b).sum()) / u if u else 1.0


def _box2d_contains(mask: np.ndarray, x: int, y: int) -> bool:
    ys, xs = np.nonzero(mask)
    return bool(len(ys)) and xs.min() <= x <= xs.max() and ys.min() <= y <= ys.max()


def evaluate_queries(grounder, scene, implicit_per_object: int = 1, min_visible_px: int = 20,
                     views: list | None = None, progress: bool = False, ablation: bool = False) -> dict:
    """Every explicit query and the first `implicit_per_object` implicit ones of queries.json, on
    every test view where the object is visible (>= min_visible_px pixels)."""
    from tqdm import tqdm

    by_id = {o.id: o for o in scene.objects}
    views = scene.test if views is None else views
    cache = [(f, f.load_visible_mask()) for f in views]
    jobs = []
    for q in scene.queries:
        if q.object_id in by_id:
            jobs.append(("explicit", q.explicit, q.object_id))
            jobs += [("implicit", t, q.object_id) for t in q.implicit[:implicit_per_object]]
    rows, abl = [], []
    for kind, text, oid in tqdm(jobs, desc="eval", unit="query", disable=not progress, file=sys.stderr):
        o = by_id[oid]
        t0 = time.perf_counter()
        res = grounder.ground(text, mode=kind)
        t_query = time.perf_counter() - t0
        box = 0.0
        if res.success:
            ob = res.objects[0]
            box = box_iou_aabb(ob.aabb_min, ob.aabb_max, o.aabb_min, o.aabb_max)
        right_name = res.target == o.name
        for f, vis_ids in cache:
            gt_vis = vis_ids == oid
            if gt_vis.sum() < min_visible_px:
                continue
            gt_amodal = f.load_complete_mask(oid)
            W, H = f.intrinsics.width, f.intrinsics.height
            t1 = time.perf_counter()
            amodal, visible = grounder.masks(res, f.intrinsics.K, f.cam_to_world, W, H)
            t_mask = time.perf_counter() - t1
            loc = False
            if res.success:
                rel, _ = grounder.relevancy_view(res.target, res.scale, f.intrinsics.K, f.cam_to_world, W, H)
                y, x = divmod(int(rel.reshape(-1).argmax()), W)
                loc = _box2d_contains(gt_vis, x, y)
            rows.append({"kind": kind, "query": text, "object": o.name, "view": f.index, "success": res.success,
                         "target_ok": right_name, "iou_visible": iou(visible, gt_vis),
                         "iou_amodal": iou(amodal, gt_amodal), "localized": loc, "box_iou": box,
                         "seconds_query": t_query, "seconds_masks": t_mask, "timings": res.timings})
            if ablation:
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


def summarise(rows: list[dict]) -> dict:
    def block(rs):
        if not rs:
            return {"pairs": 0}
        m = lambda k: float(np.mean([r[k] for r in rs]))
        return {"pairs": len(rs), "queries": len({r["query"] for r in rs}),
                "miou_visible": round(100 * m("iou_visible"), 2), "miou_amodal": round(100 * m("iou_amodal"), 2),
                "localization": round(100 * m("localized"), 2), "target_accuracy": round(100 * m("target_ok"), 2),
                "success_rate": round(100 * m("success"), 2)}

    out = {k: block([r for r in rows if r["kind"] == k]) for k in ("explicit", "implicit")}
    out["all"] = block(rows)
    per_obj: dict[str, float] = {}
    for r in rows:
        if r["kind"] == "explicit":
            per_obj[r["object"]] = r["box_iou"]
    per_obj_masks: dict[str, list] = {}
    for r in rows:
        per_obj_masks.setdefault(r["object"], []).append(r)
    def obj_block(rs):
        m = lambda k: round(100 * float(np.mean([r[k] for r in rs])), 2)
        return {"pairs": len(rs), "miou_visible": m("iou_visible"), "miou_amodal": m("iou_amodal"),
                "localization": m("localized"), "target_accuracy": m("target_ok")}

    # Per object over both kinds, and per kind: an implicit query the reasoner maps to another name
    # scores 0 whatever the 3D part does (with oracle supervision the explicit figures are the 3D part's).
    out["per_object"] = {}
    for k, rs in per_obj_masks.items():
        out["per_object"][k] = obj_block(rs)
        for kind in ("explicit", "implicit"):
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
    out["seconds"] = {"per_query_median": round(float(np.median([r["seconds_query"] for r in q.values()])), 4) if q else 0.0,
                      "masks_per_view_median": round(float(np.median([r["seconds_masks"] for r in rows])), 4) if rows else 0.0,
                      "stages_median": {k: round(float(np.median(v)), 4) for k, v in stages.items()}}
    return out
