"""`rg synth`: a synthetic table-top or room scene in the ReasoningGD layout; with --seeds, one scene
per seed as tasks, in this process or on Ray (many.py)."""
from __future__ import annotations

import time
from pathlib import Path

from .config_args import add_alias, add_sections
from .many import add_engine_args, seeds
from .options import add_common, positive, size


def cmd_synth(args, cfg) -> dict:
    from ..io.images import SceneError
    from ..synth.generator import default_objects_dir, generate_scene

    objects_dir = Path(args.objects_dir) if args.objects_dir else default_objects_dir()
    if args.objects_dir and not objects_dir.is_dir():
        raise SceneError(f"{objects_dir}: --objects-dir does not exist")
    if args.seeds is None and (args.ray is not None or args.results or args.retry_failed):
        raise ValueError("--ray, --results and --retry-failed generate many scenes: give --seeds A-B")
    t0 = time.perf_counter()
    if args.seeds is not None:
        from .many import synth_many

        summary = synth_many(args, cfg, objects_dir)
        summary["seconds"] = round(time.perf_counter() - t0, 3)
        return summary
    summary = generate_scene(args.out, cfg.synth, objects_dir, progress=not args.quiet)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def synth_task(payload: dict) -> dict:
    """One synthetic scene in a task (any process)."""
    from ..config import SynthConfig, config_from_dict
    from ..synth.generator import generate_scene

    objects_dir = Path(payload["objects_dir"]) if payload["objects_dir"] else None
    return generate_scene(payload["out"], config_from_dict(payload["config"], SynthConfig), objects_dir, progress=False)


def add_synth(sub) -> None:
    p = sub.add_parser("synth", help="generate a synthetic table-top or room scene (ReasoningGD layout)")
    p.add_argument("out", help="output scene folder (with --seeds: the folder of the scenes, OUT/scene_<seed>)")
    p.add_argument("--seeds", type=seeds, metavar="A-B",
                   help="one scene per seed (A-B inclusive, A,B,C, or 0-9,20), as tasks; --seed is then ignored")
    add_alias(p, "--views", keys="synth.views", type=positive)
    add_alias(p, "--size", keys=("synth.width", "synth.height"), type=size, help="WxH, e.g. 320x240")
    add_alias(p, "--seed", keys="synth.seed", type=int)
    add_alias(p, "--objects", keys="synth.objects", type=positive, help="number of objects on the table")
    add_alias(p, "--same-category", keys="synth.same_category", type=int,
              help="how many of them share a category with another (several cups)")
    add_alias(p, "--layout", keys="synth.layout", choices=("table", "room"),
              help="one table, or a room of --tables tables and a walk")
    add_alias(p, "--tables", keys="synth.tables", type=positive, help="tables of the room layout (default 4)")
    p.add_argument("--objects-dir", help="folder of <name>/model.urdf meshes (default: ../shared/data/objects)")
    add_alias(p, "--workers", keys="synth.workers", type=positive,
              help="render processes; with --seeds --ray (no address): Ray workers, a scene in each")
    add_engine_args(p, None)
    add_common(p)
    add_sections(p, ("synth",))
    p.set_defaults(func=cmd_synth)
