"""`rg eval`: a scene's queries on its test views (mIoU, localization, box IoU, confidence, timings);
several scenes (paths, a folder of scenes, a list file) run as one task each, in this process or on
Ray, with their aggregate (many.py)."""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from .config_args import add_alias, add_sections, was_given
from .many import add_engine_args
from .options import add_common, positive


def cmd_eval(args, cfg) -> dict:
    from .many import eval_many, is_many

    if is_many(args):
        return eval_many(args, cfg)
    one = argparse.Namespace(**vars(args))
    one.scene = args.scene[0]
    return eval_scene(one, cfg)


def eval_scene(args, cfg) -> dict:
    """One scene (args.scene a path), as `rg eval SCENE` has always run it."""
    from ..eval.grounding import evaluate_queries
    from ..grounding.build import build_grounder
    from ..io.captures import read_scene
    from ..map.store import load_map

    from ..models import ModelMissingError, apply_reasoner

    if not was_given(args, "reason.backend"):   # a backend named on the command line, not the preset's LVLM
        try:
            apply_reasoner(cfg.models.preset, cfg)
        except ModelMissingError as exc:
            print(f"rg eval: {exc}; implicit queries use reason.backend {cfg.reason.backend!r}", file=sys.stderr)
    mapper = load_map(args.map) if args.map else None
    photo = cfg.photo
    if mapper is not None and not photo.world_scale:
        # auto against a map: photos without depth take the map's world, the scale it recorded when
        # it was built from them (io/world_scale.py), metres for any other map
        photo = dataclasses.replace(photo, world_scale=float(mapper.built.get("world_scale", 1.0)))
    scene = read_scene(args.scene, photo=photo)
    if args.queries:  # anyone's own explicit and implicit queries, in the scene's queries.json format
        from ..io.queries import read_queries

        scene.queries = read_queries(args.queries, scene.objects)
    if (not scene.queries or not scene.objects) and scene.labels is None:
        raise ValueError(f"{args.scene}: rg eval needs ground-truth objects and queries (a ReasoningGD scene with "
                         "objects.json and queries.json, or a BOP scene; --queries FILE gives queries) or "
                         "LERF-OVS / 3D-OVS labels (docs/scene-formats.md)")
    if mapper is not None and args.supervision == "oracle":
        mapper.field = None  # a map's own field was trained on its own supervision
    field_seconds, as_is = args.field_seconds, False
    if (mapper is not None and getattr(mapper, "field", None) is not None and mapper.field.steps > 0
            and field_seconds is None and not was_given(args, "field.steps")):
        # a map with a trained field (a taught one too) is scored as it is: no new supervision and
        # no further training, unless --field-seconds / --field-steps asks for it
        field_seconds, as_is = 0.0, True
    t = time.perf_counter()
    grounder, report = build_grounder(scene, cfg, args.supervision, field_seconds, mapper, progress=not args.quiet)
    if as_is:
        report["field"] = {"trained": 0, "steps": grounder.field.steps, "reason": "--map: scored as it is"}
    report["seconds_build"] = round(time.perf_counter() - t, 3)
    report["eval"] = evaluate_queries(grounder, scene, args.implicit, progress=not args.quiet, ablation=args.ablation,
                                      relational=getattr(args, "relational", 0)) if scene.queries and scene.objects else {}
    from ..eval.ovs import evaluate_labels

    report["eval"].update(evaluate_labels(grounder, scene, progress=not args.quiet))   # the benchmarks' own scoring
    if scene.kind == "bop":  # how much of each amodal mask no training view saw (one viewpoint hides parts)
        from ..eval.amodal_coverage import amodal_coverage

        report["eval"]["amodal_unseen"] = amodal_coverage(scene)
    report["supervision_kind"] = args.supervision
    if args.out and "queries" in report["eval"]:
        from ..grounding.confidence import load_model, threshold
        from ..report.plots import calibration_png

        thr = threshold(load_model(cfg.models.preset, args.supervision), cfg.ground.min_confidence)
        report["plots"] = [calibration_png(report["eval"]["queries"], Path(args.out) / "risk_coverage.png", thr,
                                           f"{Path(args.scene).name}, {args.supervision} supervision")]
    return report


def eval_task(payload: dict) -> dict:
    """One scene's `rg eval` in a task (any process): the single-scene command, quiet, from the
    text embeddings a fresh process has (what ran before in the process changes no figure)."""
    from ..config import config_from_dict
    from ..perception.reasoning.text import forget_text_embeddings

    forget_text_embeddings()
    return eval_scene(argparse.Namespace(**payload["args"]), config_from_dict(payload["config"]))


def add_eval(sub) -> None:
    p = sub.add_parser("eval", help="run queries.json on the test views: mIoU, localization, box IoU, timings; "
                                    "many scenes: one task each, locally or on Ray, and their aggregate")
    p.add_argument("scene", nargs="+", help="ReasoningGD or BOP scene folder (BOP: scene_camera.json + scene_gt.json); "
                                            "several, a folder of scene folders or a text file listing them "
                                            "(one path a line): one task per scene and the aggregate")
    p.add_argument("--map", help="map file (default: build one from the scene); a map with a trained field is "
                                  "scored as it is, unless --field-seconds / --field-steps asks for more training")
    p.add_argument("--queries", help="queries.json-format file [{object_id, explicit, implicit: [...]}] "
                                     "(default: the scene's queries.json; BOP: object names + the description set)")
    p.add_argument("--supervision", default="default", choices=("default", "oracle"))
    budget = p.add_mutually_exclusive_group()
    # A fixed budget without the stop test: not field.seconds, the stop test's ceiling.
    budget.add_argument("--field-seconds", type=float, help="feature-training budget (default: config field.seconds)")
    add_alias(budget, "--field-steps", keys="field.steps", type=positive, metavar="N",
              help="train the field exactly N steps instead (default: config field.steps; 0 there = seconds)")
    p.add_argument("--implicit", type=int, default=1, help="implicit queries per object (default 1)")
    p.add_argument("--relational", type=int, default=0, metavar="N",
                   help="also N relational queries per scene from its ground truth ('the object closest to the "
                        "lemon', left of, biggest, ...; kind relational), asked from the first test view (default 0)")
    p.add_argument("--ablation", action="store_true", help="relevancy only / + reasoning / + grouping table")
    add_alias(p, "--preset", keys="models.preset",
              help="models of the default supervision: offline, paper, paper_cpu (default: config)")
    p.add_argument("--out", help="folder for PNGs: risk against coverage and reliability of the confidence; many "
                                 "scenes: aggregate.json, table.txt and scenes.png (default: the --results folder)")
    add_engine_args(p, "tasks at once on local Ray workers, --ray without an address (default: cores / --threads)",
                    threads=True)
    add_common(p)
    add_sections(p, ("map", "photo", "field", "ground", "reason", "models"))
    p.set_defaults(func=cmd_eval)
