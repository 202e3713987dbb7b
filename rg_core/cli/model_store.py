"""`rg models`: list, fetch, export to ONNX and verify the paper's models in the model cache."""
from __future__ import annotations

from pathlib import Path

from .config_args import add_sections
from .options import add_common


def cmd_models(args, cfg) -> dict:
    from .. import models

    root = Path(cfg.models.dir).expanduser() if cfg.models.dir else None
    if args.action == "list":
        return {"dir": str(root or models.models_dir()), "models": models.list_models(root),
                "presets": {p.name: {"sam": p.sam, "clip": p.clip, "lvlm": p.lvlm, "description": p.description}
                            for p in models.PRESETS.values()}}
    if not args.names:
        raise ValueError(f"rg models {args.action}: name at least one model ({', '.join(models.MODELS)})")
    from ..models.export import export
    from ..models.fetch import fetch
    from ..models.verify import verify

    run = {"fetch": lambda n: fetch(n, root, progress=not args.quiet), "export": lambda n: export(n, root),
           "verify": lambda n: verify(n, root)}[args.action]
    return {n: run(n) for n in args.names}


def add_models(sub) -> None:
    p = sub.add_parser("models", help="list, fetch, export to ONNX and verify the paper's models")
    p.add_argument("action", choices=("list", "fetch", "export", "verify"))
    p.add_argument("names", nargs="*", help="registry names (rg models list)")
    add_common(p)
    add_sections(p, ("models",))
    p.set_defaults(func=cmd_models)
