"""`rg sfm IMAGES_DIR --out SCENE`: poses for photos without them (pycolmap, CPU), written as a COLMAP
scene folder that `rg map`, `rg eval` and `rg report` read (rg_core/io/sfm.py)."""
from __future__ import annotations

from .config_args import add_alias, add_sections
from .options import add_common, positive


def cmd_sfm(args, cfg) -> dict:
    from ..io.sfm import run_sfm

    return run_sfm(args.images, args.out, cfg.sfm, progress=not args.quiet)


def add_sfm(sub) -> None:
    p = sub.add_parser("sfm", help="poses for photos without them (pycolmap: SIFT, matching, incremental mapping) "
                                   "-> a COLMAP scene folder")
    p.add_argument("images", help="folder of the photos (.png, .jpg, .jpeg at its top level)")
    p.add_argument("--out", required=True, help="scene folder to write (images/, sparse/0, database.db)")
    add_alias(p, "--matcher", keys="sfm.matcher", choices=("auto", "exhaustive", "sequential"),
              help="image pairs to match: every pair, or each photo with the next --overlap in name order")
    add_alias(p, "--overlap", keys="sfm.overlap", type=positive, help="sequential matching: photos following each")
    add_alias(p, "--camera-model", keys="sfm.camera_model",
              choices=("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"), help="COLMAP camera model")
    add_common(p)
    add_sections(p, ("sfm",))
    p.set_defaults(func=cmd_sfm)
