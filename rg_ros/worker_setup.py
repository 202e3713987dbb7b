"""The node's map worker made from its parameters (the library side): the rg config with the
node's overrides, the start-up map and the perception models (a preset's, or the named backends).
No rclpy here: the node passes its logger."""
from __future__ import annotations

import dataclasses

from .params import NodeParams
from .worker import MapWorker


def make_worker(p: NodeParams, log) -> MapWorker:
    """The library side: rg config with the node's overrides, the start-up map, the models."""
    from rg_core.config import load_config

    cfg = load_config(p.rg_config or None)
    over_map = {k: v for k, v in (("width", p.map_width), ("iters_per_keyframe", p.iters_per_keyframe),
                                  ("max_gaussians", p.max_gaussians), ("max_keyframes", p.max_keyframes))
              if v > 0}
    cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, **over_map),
                              ground=dataclasses.replace(cfg.ground, min_confidence=p.min_confidence))
    if p.preset:
        cfg.models.preset = p.preset     # its confidence model calibrates the answers
    else:
        from rg_core.models import perception_spec

        offline = perception_spec("offline")
        if (p.mask_generator, p.embedder) != (offline[0], offline[2]):
            cfg.models.preset = ""       # models of no preset: no calibrated confidence, no abstention
    mapper = None
    if p.load_map:
        from rg_core.map.store import load_map

        mapper = load_map(p.load_map)   # MapFileError: the node does not start (rg-node says why)
        log.info(f"loaded map {p.load_map}: {mapper.stats()['keyframes']} keyframes, "
                 f"{len(mapper.gaussians)} Gaussians")
    wcfg = p.worker_config()
    loader = None
    if p.preset:
        from rg_core.models import ModelError, apply_reasoner, make_perception

        try:
            apply_reasoner(p.preset, cfg)
        except ModelError as exc:  # the node runs; implicit queries use the text reasoner
            log.error(f"{exc}; implicit queries use the text reasoner")
        wcfg.mask_generator = wcfg.embedder = f"preset {p.preset}"
        loader = lambda: make_perception(p.preset, cfg.models)  # noqa: E731 - errors name the fetch command
    return MapWorker(cfg, wcfg, mapper, logger=_RosLogAdapter(log), perception_loader=loader)


class _RosLogAdapter:
    """logging.Logger-like front of an rclpy logger for the worker (printf-style arguments)."""

    def __init__(self, logger):
        self._l = logger

    def _fmt(self, msg, args):
        return str(msg) % args if args else str(msg)

    def debug(self, msg, *args):
        self._l.debug(self._fmt(msg, args))

    def info(self, msg, *args):
        self._l.info(self._fmt(msg, args))

    def warning(self, msg, *args):
        self._l.warning(self._fmt(msg, args))

    def error(self, msg, *args):
        self._l.error(self._fmt(msg, args))
