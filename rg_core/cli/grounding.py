"""`rg ground` (a query in a map: Gaussian group, boxes, explanation, masks) and `rg graph` (the
map's objects and their relations): a Grounder over a saved map with the preset's models."""
from __future__ import annotations

from pathlib import Path

from ..util import prefetch
from .config_args import add_alias, add_sections, was_given
from .options import add_common, positive

SECTIONS = ("ground", "reason", "models")   # what a Grounder over a saved map reads


def _camera_from_args(args, grounder, result):
    """The camera masks are rendered for: --view I (a keyframe), --pose FILE (JSON with K,
    cam_to_world [OpenCV axes], width, height), or the result's reference view. Returns (K,
    cam_to_world, width, height, depth, image): a keyframe's own depth and colour images, which the
    visible mask then follows as the node's does its current frame's; None for --pose."""
    if args.pose:
        from ..io.camera_json import read_camera_json

        return (*read_camera_json(args.pose), None, None)
    kfs = {kf.index: kf for kf in grounder.mapper.keyframes}
    idx = args.view if args.view is not None else result.reference_view
    if idx not in kfs:
        raise ValueError(f"--view {idx}: not a keyframe of this map; keyframes: {sorted(kfs)[:20]}...")
    kf = kfs[idx]
    return kf.K, kf.cam_to_world, kf.size[0], kf.size[1], kf.depth.numpy(), kf.rgb.numpy()


def _grounder_from_args(args, cfg):
    """The Grounder over args.map with the models of models.preset (rg ground, rg graph)."""
    from ..grounding.pipeline import Grounder
    from ..map.store import load_map

    from ..models import apply_reasoner, make_text_encoder

    preset = cfg.models.preset   # its confidence model calibrates the answer
    if not was_given(args, "reason.backend"):   # a backend named on the command line, not the preset's LVLM
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
        from ..viz.grounding import mask_summary, write_grounding_pngs

        out["masks"] = mask_summary(amodal, visible, depth, image)
        if args.out:
            out["pictures"] = write_grounding_pngs(grounder, res, K, c2w, w, h, amodal, visible, Path(args.out))
    return out


def cmd_graph(args, cfg) -> dict:
    grounder = _grounder_from_args(args, cfg)
    from ..grounding.relations import graph_json

    return {"map": args.map, **graph_json(grounder.scene_graph(), grounder.up())}


def _graph_human(result: dict) -> str:
    from ..viz.summary import graph_summary

    return graph_summary(result)


def _add_grounder_args(p) -> None:
    """What _grounder_from_args reads (rg ground, rg graph)."""
    add_alias(p, "--min-confidence", keys="ground.min_confidence", type=float, metavar="P",
              help="answers less likely right abstain (default: the preset's fitted threshold; 0: never)")
    add_alias(p, "--backend", keys="reason.backend", help="reasoning backend (text, llama_cpp, openai)")
    p.add_argument("--name", action="append", help="an object name the scene may hold (repeatable)")
    add_alias(p, "--preset", keys="models.preset",
              help="offline, paper, paper_cpu: the map's embedder (+ LVLM unless --backend)")


def add_ground(sub) -> None:
    p = sub.add_parser("ground", help="ground a query in a map: Gaussian group, boxes, explanation, masks")
    p.add_argument("map", help="map file from rg map --supervise --train-field S")
    p.add_argument("query", help="explicit ('coffee mug') or implicit ('something to drink hot tea from')")
    cam = p.add_mutually_exclusive_group()
    cam.add_argument("--view", type=int, help="the camera: masks are rendered for this keyframe (stream index; the "
                                              "visible mask follows its depth image), view-dependent words (left of, "
                                              "nearest to me) refer to it")
    cam.add_argument("--pose", help="JSON file: K, cam_to_world (OpenCV axes), width, height")
    p.add_argument("--mode", default="auto", choices=("auto", "explicit", "implicit"))
    p.add_argument("--max-results", type=positive, default=1, help="several instances ('the cups')")
    p.add_argument("--out", help="folder for PNGs: reference view, relevancy, amodal and visible masks")
    _add_grounder_args(p)
    add_common(p)
    add_sections(p, SECTIONS)
    p.set_defaults(func=cmd_ground)


def add_graph(sub) -> None:
    p = sub.add_parser("graph", help="the map's objects (names with confidence, centre, size, colour) and "
                                      "their on / near relations")
    p.add_argument("map", help="map file from rg map --supervise --train-field S")
    _add_grounder_args(p)
    add_common(p)
    add_sections(p, SECTIONS)
    p.set_defaults(func=cmd_graph, human=_graph_human)
