"""Point and teach (issue 61): what naming the objects by a click gives a map made with the offline
default models, against the same map untaught and against ground-truth 2D supervision, on scenes
nobody tuned to.

    python benchmarks/bench_teach.py [--seeds 701 702] [--rooms 703] [--ycbv ../shared/data/rgbd/ycbv_0002_bop]
                                     [--views 20] [--room-views 24] [--node-scene first] [--cli-scenes first]
                                     [--work DIR] [--out DIR] [--json] [--record]

Scenes: `rg synth` table tops (--seeds; 320x240, --views views, 7 objects, 3 sharing a category, as
bench_relations makes them), rooms (--rooms: `--layout room`, 2 tables, 8 objects, --room-views
views) and the real YCB-Video scene in BOP layout (17 train / 3 test views). Each scene is mapped and
supervised with the default models (build_grounder, the map saved), then:
- point -> object: `point.point_answer` at one simulated click per object (eval/teaching.py: the
  pixel deepest inside its visible mask, in the training view where it is largest): the median
  visible IoU of the answer's group with the object over the test views that see it (>= 20 px),
  the median over objects; warm latency: every call after the first (median, max);
- teach every click with the object's explicit name (`teach.teach`): right away (no training) the
  taught name's answer (`rg eval`'s "right": target the name, mean visible IoU >= 0.5), then the
  field re-trained (`field.train(seconds=60, converge=True)`: seconds, keyframes) and the scene's
  explicit and implicit queries (eval/grounding.evaluate_queries) scored untaught / taught /
  oracle (ground-truth masks on the same map, `rg eval --supervision oracle`);
- relational, attribute (colour) and counting queries of bench_relations' generator (synthetic
  scenes; asked from the first test camera): right-target rate untaught vs taught;
- persistence: the taught map saved, loaded, 50 more frames (the scene's frames again, new stamps),
  the refinement a node runs when idle after them (passes over all keyframes until one stops helping,
  at most map.final_iters steps), an eviction pass of --evict-share of the Gaussians from a camera
  that sees nothing; each taught name's explicit visible mIoU after, against before;
- no harm: a fresh copy of the untaught map, every other object taught (by object id), the field
  re-trained the same way; the untaught half's explicit mIoU against the untaught map's;
- the same clicks through `rg teach MAP NAME --point X Y Z --train-seconds 0` (--cli-scenes, one
  process per click, on the saved untaught map) and through the node (--node-scene: the untaught map loaded,
  /clicked_point, then ~/teach at that point, ~/save_map): the taught groups' Gaussian
  overlap (intersection over union) with the library's, taught in the same order.
Targets: taught within 5 points of oracle (explicit and implicit), relations taught >= 90 % right,
point IoU >= 0.8, warm point latency <= 0.3 s, re-training <= 30 s for a 20-keyframe map,
persistence within 2 points, no harm within 1 point. Writes teach.png (per-scene bars).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import add_output_flags, finish, pyplot, rg_json, save_figure  # noqa: E402
from bench_relations import gt_colours, make_scene, queries as relation_queries, what_it_got  # noqa: E402

RETRAIN_SECONDS = 60.0
RELATION_KINDS = {"colour": "attribute", "count": "counting"}   # every other kind: relational
MIN_PX = 20


# ------------------------------------------------------------------------------ scenes

def make_scenes(args, work: Path) -> list[tuple[str, Path, str]]:
    """[(key, folder, kind)] with kind "table", "room" or "real"; synthetic ones made in `work` unless there."""
    from rg_core.config import SynthConfig
    from rg_core.synth.generator import default_objects_dir, generate_scene

    out = []
    for seed in args.seeds:
        d = make_scene(work / f"seed_{seed}", seed, SimpleNamespace(views=args.views, objects=7, same_category=3))
        out.append((f"seed_{seed}", d, "table"))
    for seed in args.rooms:
        d = work / f"room_{seed}"
        if not d.exists():
            generate_scene(d, SynthConfig(layout="room", tables=2, objects=8, same_category=3, views=args.room_views,
                                          seed=seed), default_objects_dir(), progress=False)
        out.append((f"room_{seed}", d, "room"))
    if args.ycbv != "none" and Path(args.ycbv).is_dir():
        out.append((Path(args.ycbv).name.replace("-", "_").lower(), Path(args.ycbv), "real"))
    elif args.ycbv != "none":
        print(f"bench_teach: {args.ycbv} is missing: the real scene is skipped", file=sys.stderr)
    return out


# ------------------------------------------------------------------------------ measures

def view_ious(g, scene, res, oid: int) -> list[float]:
    """Visible IoU (as rendered) of an answer's groups with object `oid` on each test view that sees it."""
    from rg_core.eval.grounding import iou

    out = []
    for f in scene.test:
        gt = f.load_visible_mask() == oid
        if gt.sum() >= MIN_PX:
            _, vis = g.masks(res, f.intrinsics.K, f.cam_to_world, f.intrinsics.width, f.intrinsics.height)
            out.append(iou(vis, gt))
    return out


def explicit_by_object(ev: dict) -> dict[str, float]:
    return {k: v["explicit"]["miou_visible"] for k, v in ev["per_object"].items() if "explicit" in v}


def ask_relations(g, scene, qs: list[dict], cam: np.ndarray) -> list[dict]:
    """bench_relations' scoring: right = the expected target (count: the number; all: the set)."""
    rows = []
    for q in qs:
        got = what_it_got(g, q, g.ground(q["text"], cam_to_world=cam))
        rows.append({"kind": q["kind"], "group": RELATION_KINDS.get(q["kind"], "relational"), "text": q["text"],
                     "expect": q["expect"], "got": got, "right": got == q["expect"]})
    return rows


def pct(xs) -> float | None:
    xs = list(xs)
    return round(100 * float(np.mean(xs)), 1) if xs else None


def overlap(a, b) -> float:
    return len(np.intersect1d(a, b)) / max(len(np.union1d(a, b)), 1)


def groups_of(g) -> dict[str, np.ndarray]:
    """Each taught object's group in the map as it is (teach.resolve), by name (the last taught of a name)."""
    from rg_core.grounding import teach

    out = {}
    for t in g.mapper.taught:
        try:
            out[t.name] = np.asarray(teach.resolve(g, t).gaussian_ids)
        except ValueError:
            out[t.name] = np.zeros(0, np.int64)
    return out


# ------------------------------------------------------------------------------ the node

def node_teach(map_path: Path, clicks, work: Path, timeout: float = 180.0) -> dict:
    """The untaught map loaded into rg-node; each click published on /clicked_point (answered), then
    ~/teach at that point; ~/save_map -> {"saved": path, "taught": n, "seconds": per click, "refused": [...]}."""
    import subprocess
    import threading

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped
    from rg_interfaces.srv import MapFile, Teach

    from rg_ros.endurance import status_values, stop_process, write_params
    from rg_ros.run import NodeExecutor

    saved, log = work / "node_taught.rgmap", work / "node.log"
    params = write_params(work / "node.yaml", {
        "pose_source": "topic", "load_map": str(map_path), "features": True, "train_seconds_max": 0.01,
        "torch_threads": 1, "status_period": 0.3, "mask_rate": 0.0, "map_cloud_period": 0.0,
        "min_confidence": 0.0, "scene_graph_period": 0.0, "save_path": str(saved)})
    node = subprocess.Popen([sys.executable, "-m", "rg_ros.tools", "node", "--params", str(params)],
                            env=dict(os.environ), stdout=log.open("w"), stderr=subprocess.STDOUT)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    probe = rclpy.create_node("rg_bench_teach_probe", context=ctx)
    status: dict = {}
    probe.create_subscription(DiagnosticArray, "/diagnostics", lambda m: status.update(status_values(m)), 10)
    teach_cli = probe.create_client(Teach, "/rg_node/teach")
    save_cli = probe.create_client(MapFile, "/rg_node/save_map")
    clicked = probe.create_publisher(PointStamped, "/clicked_point", 10)
    ex = NodeExecutor(context=ctx)
    ex.add_node(probe)
    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()

    def wait(cond, what: str, limit: float = timeout):
        end = time.monotonic() + limit
        while time.monotonic() < end:
            if node.poll() is not None:
                raise RuntimeError(f"rg-node exited {node.returncode}: {log.read_text(errors='replace')[-2000:]}")
            v = cond()
            if v:
                return v
            time.sleep(0.1)
        raise RuntimeError(f"timed out waiting for {what}: {log.read_text(errors='replace')[-2000:]}")

    def call(client, req):
        if not client.wait_for_service(timeout_sec=60):
            raise RuntimeError(f"{client.srv_name} not discovered")
        res = client.call(req, timeout_sec=timeout)
        if res is None:
            raise RuntimeError(f"{client.srv_name}: no reply")
        return res

    st = lambda: status.get("/rg_node", {})   # noqa: E731
    out = {"seconds": [], "refused": []}
    try:
        t0 = time.perf_counter()
        wait(lambda: st().get("perception") == "ready" and st().get("keyframes", 0) > 0, "the node's map and models")
        out["start_s"] = round(time.perf_counter() - t0, 1)
        for c in clicks:
            t = time.perf_counter()
            n = (st().get("clicks") or {}).get("answered", 0)
            m = PointStamped()
            m.header.frame_id = "map"
            m.point.x, m.point.y, m.point.z = (float(v) for v in c.point)
            clicked.publish(m)
            wait(lambda: (st().get("clicks") or {}).get("answered", 0) > n, f"the click on {c.name!r} answered")
            req = Teach.Request(name=c.name)   # at the clicked point: the library's teach(g, name, point=p)
            req.point.header.frame_id = "map"
            req.point.point = m.point
            res = call(teach_cli, req)
            if not res.success:
                out["refused"].append(f"{c.name}: {res.message}")
            out["seconds"].append(time.perf_counter() - t)
        res = call(save_cli, MapFile.Request())
        if not res.success:
            raise RuntimeError(f"~/save_map: {res.message}")
    finally:
        ex.shutdown(timeout_sec=5)
        probe.destroy_node()
        ctx.try_shutdown()
        th.join(timeout=5)
        stop_process(node)
    out["saved"] = saved
    return out


# ------------------------------------------------------------------------------ one scene

def run_scene(key: str, path: Path, kind: str, args, work: Path) -> dict:
    from rg_core.config import RGConfig
    from rg_core.eval.grounding import evaluate_queries
    from rg_core.eval.teaching import simulated_clicks
    from rg_core.grounding import teach
    from rg_core.grounding.build import build_grounder
    from rg_core.grounding.pipeline import Grounder
    from rg_core.grounding.point import point_answer
    from rg_core.io.captures import read_scene
    from rg_core.map.store import load_map, save_map
    from rg_core.models import ModelMissingError, apply_reasoner

    cfg = RGConfig()
    try:   # as rg eval: the preset's reasoner for the implicit queries when it is installed
        apply_reasoner(cfg.models.preset, cfg)
    except ModelMissingError:
        pass
    scene = read_scene(path)
    names = [o.name for o in scene.objects]
    by_id = {o.id: o for o in scene.objects}
    d = work / f"{key}_maps"
    d.mkdir(parents=True, exist_ok=True)
    R: dict = {"scene": key, "kind": kind, "objects": len(scene.objects), "test_views": len(scene.test)}
    t_all = time.perf_counter()
    laps, t_lap = {}, [t_all]

    def lap(name: str) -> None:   # seconds per phase, to see where a run's time goes
        now = time.perf_counter()
        laps[name] = round(now - t_lap[0], 1)
        t_lap[0] = now
        print(f"bench_teach {key}: {name} {laps[name]:.1f} s", file=sys.stderr)

    # default supervision, untaught
    g, rep = build_grounder(scene, cfg, "default")
    R["keyframes"], R["gaussians"] = len(g.mapper.keyframes), len(g.mapper.gaussians)
    R["build_s"] = round(sum(v for k, v in rep.items() if k.startswith("seconds")) + (rep.get("field") or {}).get("seconds", 0), 1)
    R["field_stop_default"] = ((rep.get("field") or {}).get("stop") or {}).get("stopped", "-")
    untaught_map = save_map(g.mapper, d / "default.rgmap")
    lap('build')
    text, reasoner = g.text_model(), g.reasoner

    def grounder_of(m):
        return Grounder.from_map(m, cfg, text_encoder=text, reasoner=reasoner, scene_names=names)

    ev_def = evaluate_queries(g, scene, 1)
    clicks = simulated_clicks(scene)
    R["clicks"] = len(clicks)
    rel = kind != "real"
    if rel:
        f0 = scene.test[0]
        qs = relation_queries(scene, np.random.default_rng(args.seed_queries), gt_colours(scene), f0.cam_to_world,
                              f0.intrinsics.K)
        rel_def = ask_relations(g, scene, qs, f0.cam_to_world)
        lap('eval_untaught')

    # point -> object (the untaught map)
    lat, pious, pnames = [], [], []
    for c in clicks:
        t = time.perf_counter()
        res = point_answer(g, c.point)
        lat.append(time.perf_counter() - t)
        v = view_ious(g, scene, res, c.object_id) if res.success else []
        if v:
            pious.append(float(np.median(v)))
        pnames.append(res.success and res.target == c.name)
    R["point_iou_median"] = round(float(np.median(pious)), 3) if pious else 0.0
    R["point_iou_min"] = round(float(np.min(pious)), 3) if pious else 0.0
    R["point_first_s"] = round(lat[0], 3)
    R["point_warm_median_s"] = round(float(np.median(lat[1:])), 3)
    R["point_warm_max_s"] = round(float(np.max(lat[1:])), 3)
    R["point_name_right_pct"] = pct(pnames)
    lap('point')

    # teach every click, right away
    t_teach = []
    for c in clicks:
        t = time.perf_counter()
        teach.teach(g, c.name, point=c.point)
        t_teach.append(time.perf_counter() - t)
    R["teach_median_s"] = round(float(np.median(t_teach)), 3)
    lib_groups = groups_of(g)
    ev_now = evaluate_queries(g, scene, 0)   # the explicit queries: the taught names
    taught_names = {c.name for c in clicks}
    now_q = [q for q in ev_now["queries"] if q["kind"] == "explicit" and q["query"] in taught_names]
    R["right_away_pct"] = pct(q["right"] for q in now_q)
    R["explicit_now_miou"] = ev_now["explicit"]["miou_visible"]
    lap('teach_right_away')

    # the field re-trained on the names
    t = time.perf_counter()
    tr = g.field.train(seconds=RETRAIN_SECONDS, converge=True)
    R["retrain_s"] = round(time.perf_counter() - t, 1)
    R["retrain_steps"] = int(tr.get("steps", 0))
    R["retrain_stop"] = (tr.get("stop") or {}).get("stopped", "-")
    lap('retrain')
    ev_taught = evaluate_queries(g, scene, 1)
    if rel:
        rel_taught = ask_relations(g, scene, qs, f0.cam_to_world)
        for tag, rows in (("untaught", rel_def), ("taught", rel_taught)):
            R[f"relations_{tag}_pct"] = pct(r["right"] for r in rows)
            for grp in ("relational", "attribute", "counting"):
                R[f"{grp}_{tag}_pct"] = pct(r["right"] for r in rows if r["group"] == grp)
        R["relation_queries"] = len(qs)
        R["relations_wrong_taught"] = [f"{r['text']!r} -> {r['got']!r} (expected {r['expect']!r})"
                                       for r in rel_taught if not r["right"]]
    taught_map = save_map(g.mapper, d / "taught.rgmap")
    lap('eval_taught')

    # oracle supervision on the same map
    mo = load_map(untaught_map)
    mo.field = None
    go, _ = build_grounder(scene, cfg, "oracle", None, mo)
    ev_or = evaluate_queries(go, scene, 1)
    del go, mo
    lap('oracle')
    for k, ev in (("default", ev_def), ("taught", ev_taught), ("oracle", ev_or)):
        R[f"explicit_{k}_miou"] = ev["explicit"]["miou_visible"]
        R[f"implicit_{k}_miou"] = ev["implicit"].get("miou_visible", float("nan"))
    R["explicit_gap_to_oracle"] = round(R["explicit_taught_miou"] - R["explicit_oracle_miou"], 2)
    R["implicit_gap_to_oracle"] = round(R["implicit_taught_miou"] - R["implicit_oracle_miou"], 2)

    # persistence: save, load, more frames, an eviction pass
    before = explicit_by_object(ev_taught)
    m2 = load_map(taught_map)
    g2 = grounder_of(m2)
    frames = (list(scene.train) + list(scene.test)) * (1 + args.more_frames // max(len(scene.train) + len(scene.test), 1))
    kf0 = m2.keyframes[-1].index
    for i, f in enumerate(frames[:args.more_frames]):
        m2.add_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, stamp=1e4 + i)
    m2.refine(cfg.map.final_iters)   # what the node runs when idle after its last keyframe (refine_iters > 0)
    kf = m2.keyframes[0]
    far = np.eye(4)
    far[:3, 3] = [0.0, 0.0, 50.0]
    n0 = len(m2.gaussians)
    R["evicted"] = int(m2.evict(int(args.evict_share * n0), kf.K, far, *kf.size))
    R["evicted_pct"] = round(100 * R["evicted"] / max(n0, 1), 1)
    R["new_keyframes"] = sum(k.index > kf0 for k in m2.keyframes)
    ev_p = evaluate_queries(g2, scene, 0)
    after = explicit_by_object(ev_p)
    drops = [before[n] - after.get(n, 0.0) for n in before]
    R["persist_miou"] = ev_p["explicit"]["miou_visible"]
    R["persist_worst_drop"] = round(max(drops), 2) if drops else 0.0
    R["persist_drops"] = {n: round(before[n] - after.get(n, 0.0), 2) for n in before}   # per taught name (JSON only)
    R["persist_answered_pct"] = pct(q["target"] in taught_names and q["success"] for q in ev_p["queries"])
    del g2, m2
    lap('persistence')

    # no harm: half taught on a fresh copy
    g3 = grounder_of(load_map(untaught_map))
    half = [c for i, c in enumerate(sorted(clicks, key=lambda c: c.object_id)) if i % 2 == 0]
    for c in half:
        teach.teach(g3, c.name, point=c.point)
    R["noharm_retrain_steps"] = int(g3.field.train(seconds=RETRAIN_SECONDS, converge=True).get("steps", 0))
    ev3 = evaluate_queries(g3, scene, 0)
    taught_ids = {c.object_id for c in half}
    base, now = explicit_by_object(ev_def), explicit_by_object(ev3)
    others = [by_id[o.id].name for o in scene.objects if o.id not in taught_ids and by_id[o.id].name in base]
    deltas = [now.get(n, 0.0) - base[n] for n in others]
    R["noharm_mean_delta"] = round(float(np.mean(deltas)), 2) if deltas else 0.0
    R["noharm_worst_delta"] = round(float(np.min(deltas)), 2) if deltas else 0.0
    R["noharm_half_taught_miou"] = round(float(np.mean([now.get(by_id[i].name, 0.0) for i in taught_ids])), 2)
    del g3
    lap('noharm')

    # the same clicks through rg teach, one process each
    if args.cli_scenes == ["all"] or key in args.cli_scenes:
        cli_map = d / "cli.rgmap"
        shutil.copyfile(untaught_map, cli_map)
        t = time.perf_counter()
        for c in clicks:
            rg_json("teach", str(cli_map), c.name, "--point", *(f"{v:.6f}" for v in c.point), "--train-seconds", "0")
        R["cli_per_click_s"] = round((time.perf_counter() - t) / max(len(clicks), 1), 1)
        gc = grounder_of(load_map(cli_map))
        ov = [overlap(ids, lib_groups.get(n, [])) for n, ids in groups_of(gc).items()]
        R["cli_overlap_min"] = round(min(ov), 3) if ov else 0.0
        R["cli_overlap_mean"] = round(float(np.mean(ov)), 3) if ov else 0.0
        R["cli_taught"] = len(ov)
        lap('cli')
    if args.node_scene == key:
        try:
            nt = node_teach(untaught_map, clicks, d)
            gn = grounder_of(load_map(nt["saved"]))
            ov = [overlap(ids, lib_groups.get(n, [])) for n, ids in groups_of(gn).items()]
            R["node_overlap_min"] = round(min(ov), 3) if ov else 0.0
            R["node_overlap_mean"] = round(float(np.mean(ov)), 3) if ov else 0.0
            R["node_taught"] = len(ov)
            R["node_per_click_s"] = round(float(np.mean(nt["seconds"])), 2) if nt["seconds"] else 0.0
            R["node_start_s"] = nt["start_s"]
            R["node_refused"] = nt["refused"]
        except Exception as exc:  # noqa: BLE001 - no ROS 2 here, or the node failed: say so, keep the rest
            R["node_error"] = f"{type(exc).__name__}: {exc}"[:2000]
            print(f"bench_teach: node path on {key} failed: {R['node_error']}", file=sys.stderr)
    lap("node")
    R["wall_s"] = round(time.perf_counter() - t_all, 1)
    R["phases_s"] = laps
    return R


# ------------------------------------------------------------------------------ report

# (row key, label, target test or None, target text)
FIGURES = [
    ("explicit_default_miou", "explicit mIoU, default untaught", None, ""),
    ("explicit_now_miou", "explicit mIoU, taught, before re-training", None, ""),
    ("explicit_taught_miou", "explicit mIoU, taught", None, ""),
    ("explicit_oracle_miou", "explicit mIoU, oracle", None, ""),
    ("explicit_gap_to_oracle", "explicit: taught - oracle (points)", lambda v: v >= -5, ">= -5"),
    ("implicit_default_miou", "implicit mIoU, default untaught", None, ""),
    ("implicit_taught_miou", "implicit mIoU, taught", None, ""),
    ("implicit_oracle_miou", "implicit mIoU, oracle", None, ""),
    ("implicit_gap_to_oracle", "implicit: taught - oracle (points)", lambda v: v >= -5, ">= -5"),
    ("relations_untaught_pct", "relations right %, untaught", None, ""),
    ("relations_taught_pct", "relations right %, taught", lambda v: v >= 90, ">= 90"),
    ("relational_taught_pct", "relations: relational kinds, taught", None, ""),
    ("attribute_taught_pct", "relations: attribute (colour), taught", None, ""),
    ("counting_taught_pct", "relations: counting, taught", None, ""),
    ("point_iou_median", "point -> object IoU, median", lambda v: v >= 0.8, ">= 0.8"),
    ("point_iou_min", "point -> object IoU, worst object", None, ""),
    ("point_warm_median_s", "point latency warm median (s)", lambda v: v <= 0.3, "<= 0.3"),
    ("point_warm_max_s", "point latency warm max (s)", lambda v: v <= 0.3, "<= 0.3"),
    ("right_away_pct", "taught name right, right away %", lambda v: v >= 100, "100"),
    ("retrain_s", "field re-training (s)", lambda v: v <= 30, "<= 30"),
    ("keyframes", "keyframes", None, ""),
    ("retrain_stop", "re-training stopped by", None, ""),
    ("persist_worst_drop", "persistence: worst drop (points)", lambda v: v <= 2, "<= 2"),
    ("persist_miou", "persistence: explicit mIoU after", None, ""),
    ("noharm_mean_delta", "no harm: untaught half, mean change", lambda v: v >= -1, ">= -1"),
    ("noharm_worst_delta", "no harm: untaught half, worst object", None, ""),
    ("cli_overlap_min", "rg teach vs library: overlap, worst", lambda v: v >= 0.95, ">= 0.95"),
    ("node_overlap_min", "node vs library: overlap, worst", lambda v: v >= 0.95, ">= 0.95"),
]


def table(report: dict) -> list[dict]:
    scenes = report["scenes"]
    rows = []
    for key, label, test, target in FIGURES:
        vals = {s["scene"]: s.get(key) for s in scenes}
        if all(v is None for v in vals.values()):
            continue
        row = {"figure": label}
        for s, v in vals.items():
            row[s] = "-" if v is None or (isinstance(v, float) and v != v) else v
        row["target"] = target or "-"
        if test is not None:
            got = [v for v in vals.values() if isinstance(v, (int, float)) and v == v]
            row["met"] = ("yes" if all(test(v) for v in got) else
                          f"no ({sum(not test(v) for v in got)} of {len(got)})") if got else "-"
        else:
            row["met"] = "-"
        rows.append(row)
    return rows


def print_table(rows: list[dict], file=None) -> None:
    keys = list(rows[0])
    w = {k: max(len(k), *(len(str(r.get(k, ""))) for r in rows)) for k in keys}
    print("  ".join(k.ljust(w[k]) for k in keys), file=file)
    for r in rows:
        print("  ".join(str(r.get(k, "")).ljust(w[k]) for k in keys), file=file)


def to_rows(report: dict) -> tuple[list[dict], str]:
    sc = report["scenes"]
    node = next((s for s in sc if "node_overlap_min" in s or "node_error" in s), None)
    node_txt = ("node: not run" if node is None else f"node on {node['scene']}: " +
                (f"{node.get('node_per_click_s')} s a click" if "node_error" not in node else "failed"))
    notes = (f"offline models; synth seeds {' '.join(map(str, report['seeds']))} ({report['views']} views, 7 objects), "
             f"rooms {' '.join(map(str, report['rooms'])) or 'none'} (2 tables, 8 objects, {report['room_views']} views), "
             f"{report['ycbv']}; a click per object taught its name, field re-trained (stop test); persistence "
             f"+{report['more_frames']} frames, {report['evict_share']:.0%} evicted; overlap: Gaussian IoU with the "
             f"library's groups; {node_txt}; wall {report['wall_s']:.0f} s")
    return table(report), notes


def plot(report: dict, png: Path) -> Path:
    plt = pyplot()
    sc = report["scenes"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    x = np.arange(len(sc))
    for ax, kind in zip(axes, ("explicit", "implicit")):
        for j, (k, label) in enumerate((("default", "default, untaught"), ("taught", "default + taught"),
                                        ("oracle", "oracle (ground-truth masks)"))):
            vals = [s.get(f"{kind}_{k}_miou") or 0.0 for s in sc]
            ax.bar(x + (j - 1) * 0.27, vals, 0.27, label=label)
            for i, v in enumerate(vals):
                ax.text(i + (j - 1) * 0.27, v, f"{v:.0f}", ha="center", va="bottom", fontsize=6)
        ax.set_xticks(x, [s["scene"] for s in sc], fontsize=8)
        ax.set_ylim(0, 120)
        ax.set_ylabel(f"{kind} visible mIoU")
        ax.set_title(f"{kind} queries", fontsize=9)
        ax.legend(fontsize=7, loc="upper left", ncol=3)
    fig.suptitle("point and teach: one click per object, taught with its name", fontsize=9)
    save_figure(fig, png)
    return png


def main() -> int:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[701, 702], help="rg synth table-top seeds")
    ap.add_argument("--rooms", type=int, nargs="*", default=[703], help="rg synth --layout room seeds")
    ap.add_argument("--ycbv", default=str(ROOT.parent / "shared" / "data" / "rgbd" / "ycbv_0002_bop"),
                    help='a YCB-Video scene in BOP layout ("none": skip)')
    ap.add_argument("--views", type=int, default=20, help="views of each table-top scene")
    ap.add_argument("--room-views", type=int, default=24, help="views of each room")
    ap.add_argument("--only", nargs="*", default=[], help="run only these scene keys (seed_701, room_703, ycbv_0002_bop)")
    ap.add_argument("--more-frames", type=int, default=50, help="frames streamed again before the eviction pass")
    ap.add_argument("--evict-share", type=float, default=0.5, help="share of the Gaussians the eviction pass asks for")
    ap.add_argument("--cli-scenes", nargs="*", default=["first"],
                    help='scene keys taught through rg teach too ("all"; "first": the first scene)')
    ap.add_argument("--node-scene", default="first", help='the scene taught through the node ("first": the first; "none")')
    ap.add_argument("--seed-queries", type=int, default=0, help="random seed of the relational query generator")
    ap.add_argument("--work", help="keep scenes and maps here (default: a temporary folder)")
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_teach ") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        scenes = make_scenes(args, work)
        if args.only:
            scenes = [s for s in scenes if s[0] in args.only]
        if args.node_scene == "first":
            args.node_scene = scenes[0][0] if scenes else "none"
        args.cli_scenes = [scenes[0][0] if k == "first" and scenes else k for k in args.cli_scenes]
        results = []
        for key, path, kind in tqdm(scenes, desc="bench_teach", unit="scene", file=sys.stderr):
            try:
                r = run_scene(key, path, kind, args, work)
            except Exception as exc:  # noqa: BLE001 - one scene failing keeps the others' figures
                import traceback

                traceback.print_exc()
                r = {"scene": key, "kind": kind, "error": f"{type(exc).__name__}: {exc}"[:500]}
            print(json.dumps({k: v for k, v in r.items() if not isinstance(v, list)}), file=sys.stderr)
            results.append(r)
    report = {"seeds": args.seeds, "rooms": args.rooms, "ycbv": Path(args.ycbv).name if args.ycbv != "none" else "no real scene",
              "views": args.views, "room_views": args.room_views, "more_frames": args.more_frames,
              "evict_share": args.evict_share, "scenes": results, "wall_s": round(time.perf_counter() - t0, 1)}
    rows = table(report)
    print_table(rows, sys.stderr if args.json else sys.stdout)
    png = plot(report, Path(args.out) / "teach.png")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "teach.json").write_text(json.dumps(report, indent=1, default=str))
    return finish(args, report, "bench_teach", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
