"""`rg`: the headless command line. Argument parsing only; the work happens in the library.

Every subcommand accepts `--json` and then prints exactly one JSON object on stdout; progress bars
and logs go to stderr (C libraries that print to stdout are redirected while the command runs).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

from .config import ConfigError, load_config
from .perception.base import BackendError
from .util import prefetch, stdout_to_stderr


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"size must look like 320x240, got {text!r}") from exc
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size must be at least 8x8, got {text!r}")
    return w, h


def _positive(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return v


def cmd_synth(args, cfg) -> dict:
    from .io.images import SceneError
    from .synth.generator import default_objects_dir, generate_scene

    s = cfg.synth
    over = {k: v for k, v in (("views", args.views), ("objects", args.objects), ("seed", args.seed),
                              ("workers", args.workers), ("same_category", args.same_category),
                              ("layout", args.layout), ("tables", args.tables)) if v is not None}
    if args.size is not None:
        over["width"], over["height"] = args.size
    s = dataclasses.replace(s, **over)
    objects_dir = Path(args.objects_dir) if args.objects_dir else default_objects_dir()
    if args.objects_dir and not objects_dir.is_dir():
        raise SceneError(f"{objects_dir}: --objects-dir does not exist")
    t0 = time.perf_counter()
    summary = generate_scene(args.out, s, objects_dir, progress=not args.quiet)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def _floats(text: str) -> tuple:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from exc


def cmd_report(args, cfg) -> dict:
    from .report import SECTIONS, full_budgets, tiny_budgets
    from .report.runner import run_report

    over = {}
    if args.map_iters:
        over["map_iters"] = tuple(int(v) for v in args.map_iters)
    if args.field_seconds:
        over["field_seconds"] = args.field_seconds
    if args.frames:
        over["frames"] = tuple(int(v) for v in args.frames)
    if args.sizes:
        over["sizes"] = tuple(_size(v) for v in args.sizes.split(","))
    budgets = (tiny_budgets if args.tiny else full_budgets)(**over)
    sections = tuple(args.sections.split(",")) if args.sections else SECTIONS
    rep = run_report(args.scene, args.out, budgets, sections, cfg, progress=not args.quiet,
                     budgets_name="tiny" if args.tiny else "full")
    return {"report": str(Path(args.out) / "report.md"), "seconds": round(rep["seconds"], 1),
            "recommendations": rep["recommendations"], "headline": rep["headline"],
            "failed_sections": [k for k, v in rep["sections"].items() if "error" in v]}


def cmd_demo(args, cfg) -> dict:
    from .report.demo import run_demo

    return run_demo(cfg, Path(args.out), progress=not args.quiet)


def cmd_map(args, cfg) -> dict:
    from .eval.mapping import map_scene
    from .map.store import save_map

    over = {k: v for k, v in (("max_gaussians", args.max_gaussians), ("iters_per_keyframe", args.iters_per_keyframe),
                              ("width", args.width)) if v is not None}
    mcfg = dataclasses.replace(cfg.map, **over)
    preset = args.preset or cfg.models.preset
    if args.supervise:  # the preset's models must be there before the (long) mapping starts
        from .models import make_perception

        generator, embedder = make_perception(preset, cfg.models)
    mapper, report = map_scene(args.scene, mcfg, progress=not args.quiet, bag_options=_bag_options(args))
    if args.supervise:
        from .perception.supervision import supervise_map

        t = time.perf_counter()
        sset = supervise_map(mapper, generator, embedder, progress=not args.quiet)
        report["supervision"] = {**sset.stats(), "seconds_total": round(time.perf_counter() - t, 3), "preset": preset}
        if args.train_field is not None:  # the flag alone (0): until converged, field.seconds the ceiling
            from .field import FeatureField

            report["field"] = FeatureField(mapper, cfg.field).train(seconds=args.train_field or None,
                                                                    progress=not args.quiet)
        from .grounding.pipeline import Grounder

        # Name embeddings stored with the map: a later `rg ground` embeds only its query.
        report["stored_texts"] = Grounder.from_map(mapper, cfg).store_texts()
    elif args.train_field is not None:
        raise ValueError("--train-field needs --supervise (the field trains on the 2D supervision)")
    report["map"] = str(save_map(mapper, args.out))
    return report


def _bag_options(args):
    """BagOptions from `rg map`'s --bag-* arguments (None when the scene is not a bag)."""
    from .io.rosbag import BagOptions, is_bag

    if not is_bag(args.scene):
        return None
    fields = {f.name for f in dataclasses.fields(BagOptions)}
    return BagOptions(**{k: v for k, v in ((k[4:], v) for k, v in vars(args).items() if k.startswith("bag_"))
                         if k in fields and v is not None})


def _add_bag_args(p) -> None:
    """`rg map BAG` options (rg_core.io.rosbag.BagOptions; empty topics are auto-detected)."""
    from .io.ros_input import POSE_SOURCES
    from .io.rosbag import BagOptions

    d = BagOptions()
    g = p.add_argument_group("ROS 2 bags (.mcap, .db3 or a rosbag2 folder)")
    for name in ("color_topic", "depth_topic", "camera_info_topic", "pose_topic"):
        g.add_argument(f"--{name.replace('_', '-')}", dest=f"bag_{name}", help="default: auto-detect")
    g.add_argument("--pose-source", dest="bag_pose_source", choices=POSE_SOURCES, help=f"default {d.pose_source}")
    g.add_argument("--map-frame", dest="bag_map_frame", help=f"default {d.map_frame}")
    g.add_argument("--tf-max-gap", dest="bag_tf_max_gap", type=float,
                   help=f"seconds; frames in a longer TF gap are dropped (default {d.tf_max_gap}; 0 = tf2's any gap)")
    g.add_argument("--sync-slop", dest="bag_sync_slop", type=float, help=f"seconds (default {d.sync_slop})")


def _camera_from_args(args, grounder, result):
    """The camera masks are rendered for: --view I (a keyframe), --pose FILE (JSON with K,
    cam_to_world [OpenCV axes], width, height), or the result's reference view. Returns (K,
    cam_to_world, width, height, depth, image): a keyframe's own depth and colour images, which the
    visible mask then follows as the node's does its current frame's; None for --pose."""
    if args.pose:
        from .io.camera_json import read_camera_json

        return (*read_camera_json(args.pose), None, None)
    kfs = {kf.index: kf for kf in grounder.mapper.keyframes}
    idx = args.view if args.view is not None else result.reference_view
    if idx not in kfs:
        raise ValueError(f"--view {idx}: not a keyframe of this map; keyframes: {sorted(kfs)[:20]}...")
    kf = kfs[idx]
    return kf.K, kf.cam_to_world, kf.size[0], kf.size[1], kf.depth.numpy(), kf.rgb.numpy()


def _grounder_from_args(args, cfg):
    """The Grounder over args.map with the models of args.preset (rg ground, rg graph)."""
    from .grounding.pipeline import Grounder
    from .map.store import load_map

    from .models import apply_reasoner, make_text_encoder

    preset = cfg.models.preset = args.preset or cfg.models.preset   # its confidence model calibrates the answer
    if args.min_confidence is not None:
        cfg.ground.min_confidence = args.min_confidence
    if args.backend:
        cfg.reason.backend = args.backend
    else:
        apply_reasoner(preset, cfg)
    text = make_text_encoder(preset, cfg.models)  # queries in the space of the map's embeddings
    prefetch("sklearn.cluster")  # HDBSCAN's import (about a second) overlaps reading the map
    mapper = load_map(args.map)
    if getattr(mapper, "field", None) is None:
        raise ValueError(f"{args.map}: the map has no feature field; build it with rg map --supervise --train-field S")
    grounder = Grounder.from_map(mapper, cfg, text_encoder=text, scene_names=args.name or [],
                                 source=f"{args.map} (preset {preset!r})")
    return grounder


def cmd_ground(args, cfg) -> dict:
    grounder = _grounder_from_args(args, cfg)
    c2w = _camera_from_args(args, grounder, None)[1] if args.pose or args.view is not None else None
    res = grounder.ground(args.query, mode=args.mode, max_results=args.max_results, cam_to_world=c2w)
    out = res.to_json()
    if res.success and (args.out or args.view is not None or args.pose):
        K, c2w, w, h, depth, image = _camera_from_args(args, grounder, res)
        amodal, visible = grounder.masks(res, K, c2w, w, h, depth, image)
        from .viz.grounding import mask_summary, write_grounding_pngs

        out["masks"] = mask_summary(amodal, visible, depth, image)
        if args.out:
            out["pictures"] = write_grounding_pngs(grounder, res, K, c2w, w, h, amodal, visible, Path(args.out))
    return out


def cmd_graph(args, cfg) -> dict:
    grounder = _grounder_from_args(args, cfg)
    from .grounding.relations import graph_json

    return {"map": args.map, **graph_json(grounder.scene_graph(), grounder.up())}


def cmd_eval(args, cfg) -> dict:
    from .eval.grounding import evaluate_queries
    from .grounding.build import build_grounder
    from .io.captures import read_scene
    from .map.store import load_map

    if args.preset:
        cfg.models.preset = args.preset
    if args.field_steps is not None:
        cfg.field.steps = args.field_steps
    from .models import ModelMissingError, apply_reasoner

    try:
        apply_reasoner(cfg.models.preset, cfg)
    except ModelMissingError as exc:
        print(f"rg eval: {exc}; implicit queries use reason.backend {cfg.reason.backend!r}", file=sys.stderr)
    scene = read_scene(args.scene)
    if args.queries:  # anyone's own explicit and implicit queries, in the scene's queries.json format
        from .io.queries import read_queries

        scene.queries = read_queries(args.queries, scene.objects)
    if not scene.queries or not scene.objects:
        raise ValueError(f"{args.scene}: rg eval needs ground-truth objects and queries (a ReasoningGD scene with "
                         "objects.json and queries.json, or a BOP scene; --queries FILE gives queries)")
    mapper = load_map(args.map) if args.map else None
    if mapper is not None and args.supervision == "oracle":
        mapper.field = None  # a map's own field was trained on its own supervision
    t = time.perf_counter()
    grounder, report = build_grounder(scene, cfg, args.supervision, args.field_seconds, mapper, progress=not args.quiet)
    report["seconds_build"] = round(time.perf_counter() - t, 3)
    report["eval"] = evaluate_queries(grounder, scene, args.implicit, progress=not args.quiet, ablation=args.ablation)
    if scene.kind == "bop":  # how much of each amodal mask no training view saw (one viewpoint hides parts)
        from .eval.amodal_coverage import amodal_coverage

        report["eval"]["amodal_unseen"] = amodal_coverage(scene)
    report["supervision_kind"] = args.supervision
    if args.out:
        from .grounding.confidence import load_model, threshold
        from .report.plots import calibration_png

        thr = threshold(load_model(cfg.models.preset, args.supervision), cfg.ground.min_confidence)
        report["plots"] = [calibration_png(report["eval"]["queries"], Path(args.out) / "risk_coverage.png", thr,
                                           f"{Path(args.scene).name}, {args.supervision} supervision")]
    return report


def cmd_models(args, cfg) -> dict:
    from . import models

    root = Path(cfg.models.dir).expanduser() if cfg.models.dir else None
    if args.action == "list":
        return {"dir": str(root or models.models_dir()), "models": models.list_models(root),
                "presets": {p.name: {"sam": p.sam, "clip": p.clip, "lvlm": p.lvlm, "description": p.description}
                            for p in models.PRESETS.values()}}
    if not args.names:
        raise ValueError(f"rg models {args.action}: name at least one model ({', '.join(models.MODELS)})")
    from .models.export import export
    from .models.fetch import fetch
    from .models.verify import verify

    run = {"fetch": lambda n: fetch(n, root, progress=not args.quiet), "export": lambda n: export(n, root),
           "verify": lambda n: verify(n, root)}[args.action]
    return {n: run(n) for n in args.names}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rg", description="ReasonGrounder: 3D visual grounding, headless.")
    parser.add_argument("--config", help="YAML configuration file (see config/rg.example.yaml)")
    sub = parser.add_subparsers(dest="command", required=True)

    def map_models(p):   # what _grounder_from_args reads (rg ground, rg graph)
        p.add_argument("--min-confidence", type=float, metavar="P",
                       help="answers less likely right abstain (default: the preset's fitted threshold; 0: never)")
        p.add_argument("--backend", help="reasoning backend (text, llama_cpp, openai)")
        p.add_argument("--name", action="append", help="an object name the scene may hold (repeatable)")
        p.add_argument("--preset", help="offline, paper, paper_cpu: the map's embedder (+ LVLM unless --backend)")

    def common(p):
        p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
        p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("synth", help="generate a synthetic table-top or room scene (ReasoningGD layout)")
    p.add_argument("out", help="output scene folder")
    p.add_argument("--views", type=_positive)
    p.add_argument("--size", type=_size, help="WxH, e.g. 320x240")
    p.add_argument("--seed", type=int)
    p.add_argument("--objects", type=_positive, help="number of objects on the table")
    p.add_argument("--same-category", type=int, help="how many of them share a category with another (several cups)")
    p.add_argument("--layout", choices=("table", "room"), help="one table, or a room of --tables tables and a walk")
    p.add_argument("--tables", type=_positive, help="tables of the room layout (default 4)")
    p.add_argument("--objects-dir", help="folder of <name>/model.urdf meshes (default: ../shared/data/objects)")
    p.add_argument("--workers", type=_positive, help="render processes")
    common(p)
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("map", help="build a Gaussian map from a scene's training frames, evaluate on test views")
    p.add_argument("scene", help="ReasoningGD scene folder, real capture folder, BOP scene folder or ROS 2 bag "
                                  "(.mcap, .db3, folder)")
    p.add_argument("--out", required=True, help="map file to write (e.g. scene.rgmap)")
    p.add_argument("--max-gaussians", type=_positive)
    p.add_argument("--iters-per-keyframe", type=int)
    p.add_argument("--width", type=_positive, help="working image width")
    p.add_argument("--supervise", action="store_true",
                   help="also compute masks, scales, embeddings and PCA per keyframe (stored in the map)")
    p.add_argument("--train-field", type=float, metavar="SECONDS", nargs="?", const=0.0,
                   help="then train the feature field (needs --supervise): until it converges, or SECONDS")
    p.add_argument("--preset", help="models of the supervision: offline, paper, paper_cpu (default: config models.preset)")
    _add_bag_args(p)
    common(p)
    p.set_defaults(func=cmd_map)

    p = sub.add_parser("ground", help="ground a query in a map: Gaussian group, boxes, explanation, masks")
    p.add_argument("map", help="map file from rg map --supervise --train-field S")
    p.add_argument("query", help="explicit ('coffee mug') or implicit ('something to drink hot tea from')")
    cam = p.add_mutually_exclusive_group()
    cam.add_argument("--view", type=int, help="the camera: masks are rendered for this keyframe (stream index; the "
                                              "visible mask follows its depth image), view-dependent words (left of, "
                                              "nearest to me) refer to it")
    cam.add_argument("--pose", help="JSON file: K, cam_to_world (OpenCV axes), width, height")
    p.add_argument("--mode", default="auto", choices=("auto", "explicit", "implicit"))
    p.add_argument("--max-results", type=_positive, default=1, help="several instances ('the cups')")
    p.add_argument("--out", help="folder for PNGs: reference view, relevancy, amodal and visible masks")
    map_models(p)
    common(p)
    p.set_defaults(func=cmd_ground)

    p = sub.add_parser("graph", help="the map's objects (names with confidence, centre, size, colour) and "
                                      "their on / near relations")
    p.add_argument("map", help="map file from rg map --supervise --train-field S")
    map_models(p)
    common(p)
    p.set_defaults(func=cmd_graph, human=_graph_human)

    p = sub.add_parser("eval", help="run queries.json on the test views: mIoU, localization, box IoU, timings")
    p.add_argument("scene", help="ReasoningGD or BOP scene folder (BOP: scene_camera.json + scene_gt.json)")
    p.add_argument("--map", help="map file (default: build one from the scene)")
    p.add_argument("--queries", help="queries.json-format file [{object_id, explicit, implicit: [...]}] "
                                     "(default: the scene's queries.json; BOP: object names + the description set)")
    p.add_argument("--supervision", default="default", choices=("default", "oracle"))
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--field-seconds", type=float, help="feature-training budget (default: config field.seconds)")
    budget.add_argument("--field-steps", type=_positive, metavar="N",
                        help="train the field exactly N steps instead (default: config field.steps; 0 there = seconds)")
    p.add_argument("--implicit", type=int, default=1, help="implicit queries per object (default 1)")
    p.add_argument("--ablation", action="store_true", help="relevancy only / + reasoning / + grouping table")
    p.add_argument("--preset", help="models of the default supervision: offline, paper, paper_cpu (default: config)")
    p.add_argument("--out", help="folder for PNGs: risk against coverage and reliability of the confidence")
    common(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("report", help="error against run time, savings, scaling, stability: DIR/report.md + PNGs")
    p.add_argument("scene", help="ReasoningGD scene folder (objects.json and queries.json for grounding) or BOP scene")
    p.add_argument("--out", required=True, help="output folder (report.md, report.json, plots/)")
    p.add_argument("--tiny", action="store_true", help="seconds-long budgets (what the test suite runs)")
    p.add_argument("--sections", help="comma-separated subset of mapping,grounding,latency,memory,savings,"
                                      "scaling,stability,degraded (default: all)")
    p.add_argument("--map-iters", type=_floats, help="iterations per keyframe of the mapping section, e.g. 5,15,30")
    p.add_argument("--field-seconds", type=_floats, help="feature-training budgets, e.g. 10,20,40,80")
    p.add_argument("--frames", type=_floats, help="frame counts of the scaling, e.g. 25,50,100,200")
    p.add_argument("--sizes", help="image sizes of the scaling, e.g. 160x120,320x240,640x480")
    common(p)
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("models", help="list, fetch, export to ONNX and verify the paper's models")
    p.add_argument("action", choices=("list", "fetch", "export", "verify"))
    p.add_argument("names", nargs="*", help="registry names (rg models list)")
    common(p)
    p.set_defaults(func=cmd_models)

    p = sub.add_parser("demo", help="the main job on an embedded default scene")
    p.add_argument("--out", default="rg_demo", help="output folder (default: ./rg_demo)")
    common(p)
    p.set_defaults(func=cmd_demo, human=_demo_human)
    return parser


def _graph_human(result: dict) -> str:
    from .viz.summary import graph_summary

    return graph_summary(result)


def _demo_human(result: dict) -> str:
    from .viz.summary import demo_summary

    return demo_summary(result)


def _print_human(result: dict, file, human=None) -> None:
    if human is not None:
        print(human(result), file=file)
        return
    for k, v in result.items():
        print(f"{k}: {v}", file=file)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is when a record comes (a test may swap it)."""

    stream = property(lambda self: sys.stderr, lambda self, value: None)


def _log_to_stderr() -> None:
    """The library's progress notes (logging INFO of rg_core) on stderr, as the CLI's own messages."""
    lg = logging.getLogger("rg_core")
    if not any(isinstance(h, _StderrHandler) for h in lg.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        lg.addHandler(handler)
        lg.setLevel(logging.INFO)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _log_to_stderr()
    with stdout_to_stderr() as real_stdout:
        try:
            cfg = load_config(args.config)
            result, code = args.func(args, cfg), 0
        except (ConfigError, BackendError, ValueError) as exc:  # ValueError includes io.images.SceneError
            result, code = {"error": str(exc)}, 2
            print(f"rg {args.command}: error: {exc}", file=sys.stderr)
        if args.json:
            real_stdout.write(json.dumps(result) + "\n")
        elif code == 0:
            _print_human(result, real_stdout, getattr(args, "human", None))
    return code


if __name__ == "__main__":
    sys.exit(main())
