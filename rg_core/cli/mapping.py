"""`rg map`: a Gaussian map from a scene's training frames or a ROS 2 bag, evaluated on test views;
with --supervise its 2D supervision, with --train-field its feature field."""
from __future__ import annotations

import dataclasses
import time

from .config_args import add_alias, add_sections
from .options import add_common, positive


def cmd_map(args, cfg) -> dict:
    from ..eval.mapping import map_scene
    from ..map.store import save_map

    preset = cfg.models.preset
    if args.supervise:  # the preset's models must be there before the (long) mapping starts
        from ..models import make_perception

        generator, embedder = make_perception(preset, cfg.models)
    mapper, report = map_scene(args.scene, cfg.map, progress=not args.quiet, bag_options=_bag_options(args),
                               photo=cfg.photo)
    if args.supervise:
        from ..perception.supervision import supervise_map

        t = time.perf_counter()
        sset = supervise_map(mapper, generator, embedder, progress=not args.quiet)
        report["supervision"] = {**sset.stats(), "seconds_total": round(time.perf_counter() - t, 3), "preset": preset}
        if args.train_field is not None:  # the flag alone (0): until converged, field.seconds the ceiling
            from ..field import FeatureField

            report["field"] = FeatureField(mapper, cfg.field).train(seconds=args.train_field or None,
                                                                    progress=not args.quiet)
        from ..grounding.pipeline import Grounder

        # Name embeddings stored with the map: a later `rg ground` embeds only its query.
        report["stored_texts"] = Grounder.from_map(mapper, cfg).store_texts()
    elif args.train_field is not None:
        raise ValueError("--train-field needs --supervise (the field trains on the 2D supervision)")
    report["map"] = str(save_map(mapper, args.out))
    return report


def _bag_options(args):
    """BagOptions from `rg map`'s --bag-* arguments (None when the scene is not a bag)."""
    from ..io.rosbag import BagOptions, is_bag

    if not is_bag(args.scene):
        return None
    fields = {f.name for f in dataclasses.fields(BagOptions)}
    return BagOptions(**{k: v for k, v in ((k[4:], v) for k, v in vars(args).items() if k.startswith("bag_"))
                         if k in fields and v is not None})


def _add_bag_args(p) -> None:
    """`rg map BAG` options (rg_core.io.rosbag.BagOptions; empty topics are auto-detected)."""
    from ..io.ros_input import POSE_SOURCES
    from ..io.rosbag import BagOptions

    d = BagOptions()
    g = p.add_argument_group("ROS 2 bags (.mcap, .db3 or a rosbag2 folder)")
    for name in ("color_topic", "depth_topic", "camera_info_topic", "pose_topic"):
        g.add_argument(f"--{name.replace('_', '-')}", dest=f"bag_{name}", help="default: auto-detect")
    g.add_argument("--pose-source", dest="bag_pose_source", choices=POSE_SOURCES, help=f"default {d.pose_source}")
    g.add_argument("--map-frame", dest="bag_map_frame", help=f"default {d.map_frame}")
    g.add_argument("--tf-max-gap", dest="bag_tf_max_gap", type=float,
                   help=f"seconds; frames in a longer TF gap are dropped (default {d.tf_max_gap}; 0 = tf2's any gap)")
    g.add_argument("--sync-slop", dest="bag_sync_slop", type=float, help=f"seconds (default {d.sync_slop})")


def add_map(sub) -> None:
    p = sub.add_parser("map", help="build a Gaussian map from a scene's training frames, evaluate on test views")
    p.add_argument("scene", help="ReasoningGD scene folder, real capture folder, BOP scene folder or ROS 2 bag "
                                  "(.mcap, .db3, folder)")
    p.add_argument("--out", required=True, help="map file to write (e.g. scene.rgmap)")
    add_alias(p, "--max-gaussians", keys="map.max_gaussians", type=positive)
    add_alias(p, "--iters-per-keyframe", keys="map.iters_per_keyframe", type=int)
    add_alias(p, "--width", keys="map.width", type=positive, help="working image width")
    p.add_argument("--supervise", action="store_true",
                   help="also compute masks, scales, embeddings and PCA per keyframe (stored in the map)")
    p.add_argument("--train-field", type=float, metavar="SECONDS", nargs="?", const=0.0,
                   help="then train the feature field (needs --supervise): until it converges, or SECONDS")
    add_alias(p, "--preset", keys="models.preset",
              help="models of the supervision: offline, paper, paper_cpu (default: config models.preset)")
    _add_bag_args(p)
    add_common(p)
    add_sections(p, ("map", "photo", "field", "models"))
    p.set_defaults(func=cmd_map)
