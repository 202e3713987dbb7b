"""`rg`: the headless command line. Argument parsing only; the work happens in the library.

Every subcommand accepts `--json` and then prints exactly one JSON object on stdout; progress bars
and logs go to stderr (C libraries that print to stdout are redirected while the command runs).
The fields of the config sections a subcommand reads are options too (`--map.width 160`,
config_args.py): defaults in code < `--config FILE` < the command line. Each subcommand lives in
the module of its capability (synthesis, sfm, mapping, grounding, teaching, evaluation, reporting,
model_store).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys

from ..batch import EngineError
from ..config import ConfigError, load_config
from ..perception.base import BackendError
from ..util import join_prefetches, stdout_to_stderr
from . import evaluation, grounding, mapping, model_store, reporting, sfm, synthesis, teaching
from .config_args import apply_overrides


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rg", description="ReasonGrounder: 3D visual grounding, headless.")
    parser.add_argument("--config", help="YAML configuration file (see config/rg.example.yaml)")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (synthesis.add_synth, sfm.add_sfm, mapping.add_map, grounding.add_ground, grounding.add_graph, evaluation.add_eval,
                teaching.add_point, teaching.add_teach, reporting.add_report, model_store.add_models, reporting.add_demo):
        add(sub)
    return parser


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
            cfg = apply_overrides(load_config(args.config), args)
            result, code = args.func(args, cfg), 0
        except (ConfigError, BackendError, EngineError, ValueError) as exc:  # ValueError includes io.images.SceneError
            result, code = {"error": str(exc)}, 2
            print(f"rg {args.command}: error: {exc}", file=sys.stderr)
        if code == 0 and hasattr(result, "write_to"):   # many scenes: streamed from the files it wrote
            result.write_to(real_stdout, args.json)
        elif args.json:
            real_stdout.write(json.dumps(result) + "\n")
        elif code == 0:
            _print_human(result, real_stdout, getattr(args, "human", None))
    join_prefetches()   # never exit while a background import is loading a native library
    return code
