"""Shared state of one report run: the scene, cached map runs and trained grounders, so that
sections that need the same default map build it once."""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

from ..config import RGConfig
from ..eval.mapping import evaluate_views
from ..io.captures import read_scene
from ..map.mapper import Mapper
from ..map.run import build_map, stream_frames
from .budgets import Budgets

log = logging.getLogger(__name__)


class Context:
    def __init__(self, scene_dir, out: Path, budgets: Budgets, cfg: RGConfig | None = None, progress: bool = True):
        self.scene_dir, self.out, self.b, self.progress = Path(scene_dir), Path(out), budgets, progress
        cfg = cfg or RGConfig()
        self.cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, **budgets.map_overrides),
                                       photo=dataclasses.replace(cfg.photo, **budgets.photo_overrides),
                                       field=dataclasses.replace(cfg.field, **budgets.field_overrides))
        self.scene = read_scene(scene_dir, photo=self.cfg.photo)
        # no depth on any training frame: maps come from the photo-only fit (map/photo_fit.py)
        self.photo = bool(self.scene.train) and all(f.depth_path is None for f in self.scene.train)
        self.cache: dict = {}
        self.plots = self.out / "plots"
        self.plots.mkdir(parents=True, exist_ok=True)

    def log(self, msg: str) -> None:
        log.info("[report] %s", msg)

    # ------------------------------------------------------------------------------ maps

    def map_run(self, key, frames=None, mapper_cls=Mapper, **over) -> tuple[Mapper, dict]:
        """Map the training frames (or `frames`) with cfg.map + `over`; evaluate on the clean test
        views. Cached by `key`. Row: seconds, keyframes, gaussians, psnr, depth error (mm). A scene
        without depth is fitted from its photos instead (map.run.build_map: the photo section's
        budget; `over` applies to the map config), and its row keeps the fit's summary ("built")."""
        if key in self.cache:
            return self.cache[key]
        mcfg = dataclasses.replace(self.cfg.map, **over)
        if self.photo:
            if frames is not None or mapper_cls is not Mapper:
                raise ValueError(f"{self.scene_dir}: this section streams RGB-D frames; the scene has no depth images")
            mapper, built = build_map(self.scene, mcfg, self.cfg.photo, self.progress)
            q = evaluate_views(mapper, self.scene.test)
            row = {"seconds": built["seconds"], "keyframes": len(mapper.keyframes), "gaussians": len(mapper.gaussians),
                   "psnr": q.get("psnr", float("nan")), "psnr_valid_depth": float("nan"),
                   "depth_err_mm": float("nan"), "coverage": q.get("coverage", float("nan")), "built": built}
            self.log(f"map {key} (photo fit): {({k: v for k, v in row.items() if k != 'built'})}")
            self.cache[key] = (mapper, row)
            return mapper, row
        mapper = mapper_cls(mcfg)
        secs = stream_frames(mapper, frames if frames is not None else self.scene.train, self.progress, desc=str(key))
        secs += mapper.refine(mcfg.final_iters)
        q = evaluate_views(mapper, self.scene.test)
        row = {"seconds": round(secs, 3), "keyframes": len(mapper.keyframes), "gaussians": len(mapper.gaussians),
               "psnr": q.get("psnr", float("nan")), "psnr_valid_depth": q.get("psnr_valid_depth", float("nan")),
               "depth_err_mm": 1000 * q.get("depth_abs_error_median_m", float("nan")),
               "coverage": q.get("coverage", float("nan"))}
        self.log(f"map {key}: {row}")
        self.cache[key] = (mapper, row)
        return mapper, row

    def base(self) -> tuple[Mapper, dict]:
        """The map at the configured default budget (shared by most sections)."""
        return self.map_run(("iters", self.cfg.map.iters_per_keyframe))

    # ------------------------------------------------------------------------------ grounding

    def reasoner(self):
        if "reasoner" not in self.cache:
            from ..perception.reasoning import TextReasoner

            self.cache["reasoner"] = TextReasoner()
        return self.cache["reasoner"]

    def grounder(self, mapper: Mapper, seconds: float, cfg: RGConfig | None = None, supervision: str = "oracle"):
        """A fresh field with `supervision` (oracle unless named), trained `seconds` -> (Grounder, train report)."""
        from ..grounding.build import build_grounder

        mapper.field = None  # a fresh field, not the one a previous grounder trained
        mapper.supervision = None
        g, rep = build_grounder(self.scene, cfg or self.cfg, supervision, seconds, mapper, progress=self.progress,
                                reasoner=self.reasoner())
        return g, rep

    def evaluate(self, grounder, implicit: int | None = None) -> dict:
        from ..eval.grounding import evaluate_queries

        imp = self.b.implicit_per_object if implicit is None else implicit
        return evaluate_queries(grounder, self.scene, imp, progress=self.progress)

    def trained(self):
        """A grounder on the default map: the grounding section's (largest budget) if it ran, else a
        field trained `savings_field_seconds`, which is also the baseline of savings and degraded."""
        if "grounder_main" in self.cache:
            return self.cache["grounder_main"]
        return self.field_baseline()[0]

    def field_baseline(self):
        """(grounder, eval) on the default map with a field trained `savings_field_seconds`."""
        if "field_baseline" not in self.cache:
            mapper, _ = self.base()
            g, rep = self.grounder(mapper, self.b.savings_field_seconds)
            t = time.perf_counter()
            ev = self.evaluate(g)
            self.cache["field_baseline"] = (g, ev, rep.get("field", {}), time.perf_counter() - t)
        return self.cache["field_baseline"][:2]

    # ------------------------------------------------------------------------------ scenes

    def synth_scene(self, views: int, width: int, height: int) -> Path:
        """A synthetic scene in OUT/scenes (generated once, reused by later runs)."""
        from ..config import SynthConfig
        from ..synth.generator import default_objects_dir, generate_scene

        d = self.out / "scenes" / f"synth_{views}v_{width}x{height}_o{self.b.synth_objects}"
        if not (d / "transforms_train.json").is_file():
            self.log(f"generating {d.name}")
            s = SynthConfig(views=views, width=width, height=height, objects=self.b.synth_objects, seed=0,
                            workers=1 if views * width * height < 200_000 else 2)
            generate_scene(d, s, default_objects_dir(), progress=self.progress)
        return d
