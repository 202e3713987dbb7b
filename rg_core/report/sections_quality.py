"""Report sections on quality against time: mapping, grounding, query latency, savings, degraded
inputs. Each takes the Context and returns {"text", "tables", "plots", "data"}."""
from __future__ import annotations

import statistics
import time

from ..config import MapConfig
from ..field.converge import describe
from .inputs import SeedEverywhereMapper, degrade, resized_map, with_section
from .plots import line_plot, photo_psnr_png
from .scaling import growth_exponent


def _table(title, columns, rows):
    return {"title": title, "columns": list(columns), "rows": [list(r) for r in rows]}


def mapping(ctx) -> dict:
    """PSNR and depth error against mapping seconds, one run per iterations-per-keyframe budget and
    one with the per-keyframe stop test (map.converge_tol 0.02, ceiling the largest budget), marked."""
    if ctx.photo:
        return _photo_mapping(ctx)
    default = MapConfig().iters_per_keyframe
    rows = []
    for it in ctx.b.map_iters:
        if it < 0:
            raise ValueError(f"iters_per_keyframe must be >= 0, got {it}")
        _, r = ctx.map_run(("iters", it), iters_per_keyframe=it)
        rows.append({"iters": it, **r})
    top = max(ctx.b.map_iters)
    _, conv = ctx.map_run(("converge", top), iters_per_keyframe=top, converge_tol=0.02)
    conv = {"iters": f"stop test (<= {top})", **conv}
    mark = [r for r in rows if r["iters"] == default] or [r for r in rows if r["iters"] == ctx.cfg.map.iters_per_keyframe]
    marks = lambda k: [(r["seconds"], r[k], f"default ({r['iters']} it/kf)") for r in mark] + [  # noqa: E731
        (conv["seconds"], conv[k], "stop test")]
    png = line_plot(ctx.plots / "mapping_error_vs_time.png", [
        {"x": "mapping seconds", "y": "test PSNR (dB)", "logx": True, "mark": marks("psnr"),
         "series": [("PSNR", [r["seconds"] for r in rows], [r["psnr"] for r in rows])]},
        {"x": "mapping seconds", "y": "median |depth error| (mm)", "logx": True, "mark": marks("depth_err_mm"),
         "series": [("depth", [r["seconds"] for r in rows], [r["depth_err_mm"] for r in rows])]}],
        "Mapping: error against run time (iterations per keyframe)")
    cols = ("it/kf", "seconds", "keyframes", "Gaussians", "PSNR dB", "PSNR valid-depth dB", "depth err mm", "coverage")
    t = [(r["iters"], r["seconds"], r["keyframes"], r["gaussians"], r["psnr"], r["psnr_valid_depth"], r["depth_err_mm"],
          r["coverage"]) for r in rows + [conv]]
    return {"text": [f"{len(ctx.scene.train)} training frames, {len(ctx.scene.test)} test views; final refinement "
                     f"{ctx.cfg.map.final_iters} iterations; default {default} it/kf."],
            "tables": [_table("Mapping budgets", cols, t)], "plots": [png], "data": rows, "stop": conv}


def _photo_mapping(ctx) -> dict:
    """A scene without depth: one photo-only fit (the photo section's budget) and its held-out PSNR
    against seconds (map/photo_fit.py's fit_summary: rows step, seconds, PSNR, Gaussians)."""
    _, row = ctx.base()
    fit = row["built"]["photo"]
    curve = fit["heldout_psnr"]
    png = photo_psnr_png(curve, ctx.plots / "photo_heldout_psnr_vs_time.png", fit["stopped"],
                         "Photo-only fit: held-out PSNR against run time")
    cols = ("step", "seconds", "held-out PSNR dB", "Gaussians")
    t = {"seconds": row["seconds"], "steps": fit["steps"], "stopped": fit["stopped"], "psnr": row["psnr"],
         "gaussians": row["gaussians"], "keyframes": row["keyframes"]}
    return {"text": [f"{len(ctx.scene.train)} training photos without depth, {len(ctx.scene.test)} test views: a "
                     f"photo-only 3DGS fit ({fit['steps']} steps, stopped: {fit['stopped']}; world scale "
                     f"{row['built']['world_scale']:.4g}, {row['built']['world_rule']} rule); the held-out views "
                     f"({len(fit.get('heldout_views', []))} of the training photos, evenly spaced) are not trained on "
                     f"until the stop is decided (step {fit.get('decided', fit['steps'])}), then join for the rest."],
            "tables": [_table("Photo-only fit", list(t), [list(t.values())]),
                       _table("Held-out PSNR against time", cols, curve)],
            "plots": [png], "data": [{"iters": "photo fit", **{k: v for k, v in row.items() if k != "built"}}],
            "photo": fit}


def _ground_row(secs, steps, ev):
    e, i = ev.get("explicit", {}), ev.get("implicit", {})
    return {"field_seconds": round(secs, 2), "steps": steps, "explicit_visible": e.get("miou_visible", float("nan")),
            "explicit_amodal": e.get("miou_amodal", float("nan")), "implicit_visible": i.get("miou_visible", float("nan")),
            "implicit_amodal": i.get("miou_amodal", float("nan")), "localization": ev.get("all", {}).get("localization", float("nan")),
            "query_s": ev.get("seconds", {}).get("per_query_median", float("nan"))}


def grounding(ctx) -> dict:
    """mIoU (visible/amodal, explicit/implicit) against feature-training seconds: one field with
    oracle supervision, evaluated after each cumulative budget; a second field (same seed) trained by
    the stop test is evaluated and marked. Also against frames-to-first-answer time (map +
    supervision + field)."""
    budgets = sorted(ctx.b.field_seconds)
    if not budgets or budgets[0] <= 0:
        raise ValueError(f"field budgets must be positive seconds, got {ctx.b.field_seconds}")
    mapper, mrow = ctx.base()
    ctx.log("grounding: field until the stop test")
    gs, rep = ctx.grounder(mapper, None)
    stop = {**_ground_row(rep["field"]["seconds"], gs.field.steps, ctx.evaluate(gs)), "budget": "stop test",
            "rule": describe(gs.field.stop)}
    g, rep = ctx.grounder(mapper, 0.0)
    sup_s = rep.get("supervision", {}).get("seconds", 0.0)
    rows, done = [], 0.0
    for b in budgets:
        ctx.log(f"grounding: field to {b:g} s")
        done += g.field.train(seconds=b - done, progress=ctx.progress)["seconds"]
        rows.append(_ground_row(done, g.field.steps, ctx.evaluate(g)))
        rows[-1]["budget"] = b
    ctx.cache["grounder_main"], ctx.cache["grounding_rows"] = g, rows
    for r in rows + [stop]:
        r["first_answer_s"] = round(mrow["seconds"] + sup_s + r["field_seconds"], 2)
    series = lambda x: [(f"{k} {v}", [r[x] for r in rows], [r[f"{k}_{v}"] for r in rows])  # noqa: E731
                        for k in ("explicit", "implicit") for v in ("visible", "amodal")]
    lab = f"stop test ({stop['steps']} steps)"
    png = line_plot(ctx.plots / "grounding_miou_vs_field_seconds.png", [
        {"x": "feature-training seconds", "y": "mIoU (%)", "series": series("field_seconds"), "logx": True,
         "mark": [(stop["field_seconds"], stop["explicit_visible"], lab)]},
        {"x": "frames-to-first-answer seconds (map + supervision + field)", "y": "mIoU (%)", "logx": True,
         "series": series("first_answer_s"), "mark": [(stop["first_answer_s"], stop["explicit_visible"], lab)]}],
        "Grounding (oracle 2D supervision): mIoU against run time")
    cols = ("budget s", "trained s", "steps", "first answer s", "explicit visible", "explicit amodal", "implicit visible",
            "implicit amodal", "localization %", "query s (median)")
    t = [(r["budget"], r["field_seconds"], r["steps"], r["first_answer_s"], r["explicit_visible"], r["explicit_amodal"],
          r["implicit_visible"], r["implicit_amodal"], r["localization"], r["query_s"]) for r in rows + [stop]]
    return {"text": [f"Map at the default budget ({len(mapper.gaussians)} Gaussians, {mrow['seconds']:.1f} s); oracle "
                     f"supervision (ground-truth visible masks, MiniLM name embeddings, {sup_s:.1f} s) measures the 3D "
                     f"part. The default trains until the stop test: {stop['rule']}."],
            "tables": [_table("mIoU (%) against feature-training time", cols, t)], "plots": [png], "data": rows,
            "stop": stop}


def _latency(ctx, g, queries) -> dict:
    from ..grounding.pipeline import Grounder

    times, clusters, ok = [], [], 0
    for q in queries:
        t = time.perf_counter()
        r = g.ground(q, mode="explicit")
        times.append(time.perf_counter() - t)
        clusters.append(r.timings.get("cluster", 0.0))
        ok += int(r.success)
    assert isinstance(g, Grounder)
    return {"median_s": statistics.median(times), "max_s": max(times), "cluster_median_s": statistics.median(clusters),
            "success": ok / len(queries)}


def latency(ctx) -> dict:
    """Median Grounder.ground latency against map size (subsets, or jittered copies up to 100k)."""
    from ..grounding.pipeline import Grounder

    if any(n < 1 for n in ctx.b.latency_sizes):
        raise ValueError(f"map sizes must be >= 1 Gaussian, got {ctx.b.latency_sizes}")
    g0 = ctx.trained()
    N = len(g0.mapper.gaussians)
    queries = [q.explicit for q in ctx.scene.queries][: max(1, ctx.b.latency_queries)]
    g0.ground(queries[0], mode="explicit")  # warm-up: text model, vocabulary
    rows = []
    for n in sorted(set(ctx.b.latency_sizes) | {N}):
        m, f = (g0.mapper, g0.field) if n == N else resized_map(g0.mapper, g0.field, n)
        g = Grounder(m, f, ctx.cfg, reasoner=g0.reasoner, text_encoder=g0._text, scene_names=g0.scene_names)
        rows.append({"gaussians": n, "default_map": n == N, **_latency(ctx, g, queries)})
        ctx.log(f"latency {n} Gaussians: {rows[-1]}")
    k = growth_exponent([r["gaussians"] for r in rows], [r["median_s"] for r in rows])
    mark = [(r["gaussians"], r["median_s"], "default map") for r in rows if r["default_map"]]
    png = line_plot(ctx.plots / "latency_vs_map_size.png", [
        {"x": "Gaussians in the map", "y": "seconds per query", "logx": True, "logy": True, "mark": mark,
         "series": [("median", [r["gaussians"] for r in rows], [r["median_s"] for r in rows]),
                    ("max", [r["gaussians"] for r in rows], [r["max_s"] for r in rows]),
                    ("clustering (median)", [r["gaussians"] for r in rows], [max(r["cluster_median_s"], 1e-4) for r in rows])]}],
        "Query latency against map size")
    cols = ("Gaussians", "median s", "max s", "clustering median s", "success", "map")
    t = [(r["gaussians"], r["median_s"], r["max_s"], r["cluster_median_s"], r["success"],
          "default" if r["default_map"] else ("subset" if r["gaussians"] < N else "jittered copies")) for r in rows]
    return {"text": [f"{len(queries)} explicit queries per size, each on a fresh Grounder (clusters not cached across sizes); "
                     f"max_cluster_points {ctx.cfg.ground.max_cluster_points}. Growth exponent of the median: {k:.2f}."],
            "tables": [_table("Query latency", cols, t)], "plots": [png], "data": {"rows": rows, "exponent": k}}


class _ForceMode:
    """A Grounder whose ground() always uses one reasoning mode (turning the explicit shortcut off)."""

    def __init__(self, g, mode):
        self._g, self._mode = g, mode

    def ground(self, query, mode="auto", **kw):
        return self._g.ground(query, mode=self._mode, **kw)

    def __getattr__(self, name):
        return getattr(self._g, name)


def _saving_row(name, off_by, on, off, t_key, metrics):
    saved = off[t_key] - on[t_key]
    row = {"saving": name, "turned off by": off_by, "seconds on": on[t_key], "seconds off": off[t_key],
           "time saved s": saved, "time saved %": 100 * saved / off[t_key] if off[t_key] else float("nan")}
    for m in metrics:
        row[f"{m} on"], row[f"{m} off"], row[f"{m} change"] = on[m], off[m], on[m] - off[m]
    return row


def _field_stop_saving(ctx, mapper) -> dict:
    """The field's stop test against training the whole ceiling (field.seconds): seconds of training,
    mIoU change (the grounding section's row at the ceiling when it ran, else trained here)."""
    ceiling = ctx.cfg.field.seconds
    gs, rep = ctx.grounder(mapper, None)
    on = {**_ground_row(0, 0, ctx.evaluate(gs)), "s": rep["field"]["seconds"]}
    off = next((r for r in ctx.cache.get("grounding_rows", []) if r["budget"] == ceiling), None)
    if off is None:
        go, rep_o = ctx.grounder(mapper, ceiling)
        off = {**_ground_row(rep_o["field"]["seconds"], go.field.steps, ctx.evaluate(go))}
    off = {**off, "s": off["field_seconds"]}
    return _saving_row(f"field stop test ({gs.field.steps} steps)", f"train the whole field.seconds ({ceiling:g} s)",
                       on, off, "s", ("explicit_visible", "explicit_amodal", "implicit_visible"))


def _views_saving(ctx, mapper) -> dict:
    """Default supervision embedding each object in at most models.views_per_object views against
    every mask: supervision seconds and mIoU with default supervision (fields trained alike)."""
    rows = {}
    for vpo in (ctx.cfg.models.views_per_object, 0):
        g, rep = ctx.grounder(mapper, ctx.b.savings_field_seconds, with_section(ctx.cfg, "models", views_per_object=vpo),
                              supervision="default")
        rows[vpo] = {**_ground_row(0, 0, ctx.evaluate(g)), "s": rep["supervision"]["seconds"]}
    mapper.supervision = mapper.field = None  # later rows supervise with the oracle again
    return _saving_row(f"embed each object in {ctx.cfg.models.views_per_object} views (default supervision)",
                       "views_per_object=0 (every mask)", rows[ctx.cfg.models.views_per_object], rows[0], "s",
                       ("explicit_visible", "explicit_amodal", "implicit_visible"))


def savings(ctx) -> dict:
    """Each saving of the pipeline against turning it off, same scene, same run."""
    _, base = ctx.base()
    mrows = []
    for name, off_by, kw in (
            ("keyframe skipping", "kf_new_fraction=-1 (every frame a keyframe)", dict(kf_new_fraction=-1.0)),
            ("seed only unexplained pixels", "SeedEverywhereMapper (seed every valid-depth block)", dict(mapper_cls=SeedEverywhereMapper)),
            ("pruning", "prune_opacity=0, prune_scale=1e9", dict(prune_opacity=0.0, prune_scale=1e9)),
            ("coarse-to-fine keyframe iterations", "coarse_share=0 (all at full resolution)", dict(coarse_share=0.0)),
            ("final refinement stop test", "refine_tol=0 (all final_iters)", dict(refine_tol=0.0))):
        _, off = ctx.map_run(("off", name), **kw)
        mrows.append(_saving_row(name, off_by, base, off, "seconds", ("psnr", "depth_err_mm", "gaussians")))
    grows = []
    g, ev_on = ctx.field_baseline()
    on = _ground_row(0, 0, ev_on)
    on["s"] = ev_on["seconds"]["per_query_median"]
    from ..grounding.pipeline import Grounder

    N = len(g.mapper.gaussians)
    gs, where = g, f"{N}"
    if N > ctx.b.cluster_all_max:  # HDBSCAN on everything is super-linear: compare on a subset map
        m, f = resized_map(g.mapper, g.field, ctx.b.cluster_all_max)
        gs = Grounder(m, f, ctx.cfg, reasoner=g.reasoner, text_encoder=g._text, scene_names=g.scene_names)
        where = f"{ctx.b.cluster_all_max} (random subset of the {N}-Gaussian map)"
    ga = Grounder(gs.mapper, gs.field, with_section(ctx.cfg, "ground", max_cluster_points=0), reasoner=g.reasoner,
                  text_encoder=g._text, scene_names=g.scene_names)
    ev, ev_e = ctx.evaluate(ga, implicit=0), ctx.evaluate(gs, implicit=0)
    a, b = _ground_row(0, 0, ev_e), _ground_row(0, 0, ev)
    a["s"], b["s"] = ev_e["seconds"]["per_query_median"], ev["seconds"]["per_query_median"]
    grows.append(_saving_row(f"cluster at most {ctx.cfg.ground.max_cluster_points} Gaussians (map of {where})", "max_cluster_points=0",
                             a, b, "s", ("explicit_visible", "explicit_amodal")))
    ev_i = ctx.evaluate(_ForceMode(g, "implicit"), implicit=0)
    ev_x = ctx.evaluate(_ForceMode(g, "explicit"), implicit=0)
    a, b = _ground_row(0, 0, ev_x), _ground_row(0, 0, ev_i)
    a["s"] = ev_x["seconds"]["stages_median"].get("reason", float("nan"))
    b["s"] = ev_i["seconds"]["stages_median"].get("reason", float("nan"))
    grows.append(_saving_row("skip the reasoning model for explicit queries", "mode=implicit for explicit queries",
                             a, b, "s", ("explicit_visible", "explicit_amodal")))
    # Field renders at most train_width wide: steps per second against the map's working width.
    full_w = max(kf.size[0] for kf in g.mapper.keyframes)
    if full_w > ctx.cfg.field.train_width:
        cfg_w = with_section(ctx.cfg, "field", train_width=full_w)
        gw, rep = ctx.grounder(g.mapper, ctx.b.savings_field_seconds, cfg_w)
        ev_w = ctx.evaluate(gw)
        rep_on = ctx.cache["field_baseline"][2]
        a, b = _ground_row(0, 0, ev_on), _ground_row(0, 0, ev_w)
        a["s"] = rep_on["seconds"] / max(rep_on["steps"], 1)
        b["s"] = rep["field"]["seconds"] / max(rep["field"]["steps"], 1)
        grows.append(_saving_row(f"train the field at {ctx.cfg.field.train_width} px", f"train_width={full_w}",
                                 a, b, "s", ("explicit_visible", "explicit_amodal", "implicit_visible")))
    grows.append(_field_stop_saving(ctx, g.mapper))
    grows.append(_views_saving(ctx, g.mapper))
    mcols = ("saving", "turned off by", "seconds on", "seconds off", "time saved s", "time saved %", "psnr change",
             "depth_err_mm change", "gaussians on", "gaussians off")
    gcols = ("saving", "turned off by", "seconds on", "seconds off", "time saved s", "time saved %",
             "explicit_visible change", "explicit_amodal change")
    return {"text": [f"Mapping savings: total mapping seconds against the default map ({base['seconds']:.1f} s); "
                     "error change = on - off (PSNR dB, depth mm: negative depth change = saving is more accurate).",
                     "Grounding savings: seconds per query (clustering), reasoning seconds per query (reasoner), "
                     f"seconds per field step (train width; field trained {ctx.b.savings_field_seconds:g} s), "
                     "field training seconds (stop test) or supervision seconds (views per object); mIoU in %."],
            "tables": [_table("Mapping savings", mcols, [[r.get(c, "") for c in mcols] for r in mrows]),
                       _table("Grounding savings", gcols, [[r.get(c, "") for c in gcols] for r in grows])],
            "plots": [], "data": {"mapping": mrows, "grounding": grows}}


def degraded(ctx) -> dict:
    """Depth noise, missing depth and pose noise on the training frames: error change against clean."""
    _, base = ctx.base()
    _, ev0 = ctx.field_baseline()
    clean = {**base, **_ground_row(0, 0, ev0)}
    rows = [{"case": "clean", **clean}]
    for kind in ctx.b.degraded:
        m, r = ctx.map_run(("degraded", kind), frames=degrade(ctx.scene.train, kind))
        g, _ = ctx.grounder(m, ctx.b.savings_field_seconds)
        rows.append({"case": kind, **r, **_ground_row(0, 0, ctx.evaluate(g))})
    keys = ("psnr", "depth_err_mm", "explicit_visible", "explicit_amodal", "implicit_amodal")
    for r in rows:
        for k in keys:
            r[f"d_{k}"] = r[k] - clean[k]
    cols = ("case", "seconds", "gaussians", "psnr", "d_psnr", "depth_err_mm", "d_depth_err_mm", "explicit_visible",
            "d_explicit_visible", "explicit_amodal", "d_explicit_amodal", "implicit_amodal", "d_implicit_amodal")
    return {"text": ["Training frames degraded (seeded), test views clean; grounding with oracle masks on the clean "
                     f"frames and a field trained {ctx.b.savings_field_seconds:g} s. d_ = change against clean."],
            "tables": [_table("Degraded inputs", cols, [[r[c] for c in cols] for r in rows])], "plots": [], "data": rows}


