"""Everything a query needs, built from a scene: map -> 2D supervision -> feature field -> Grounder.
One function so `rg ground`, `rg eval`, `rg demo`, the benchmarks and the tests build alike."""
from __future__ import annotations

import logging
import time

from ..config import RGConfig
from ..field import FeatureField
from ..map.mapper import Mapper
from ..map.run import build_map
from .pipeline import Grounder

log = logging.getLogger(__name__)


def supervise(mapper: Mapper, scene, kind: str, text_encoder, progress: bool = False,
              cfg: RGConfig | None = None) -> dict:
    """`default`: the mask generator and embedder of cfg.models.preset (offline: RGB-D masks and ConSE);
    `oracle`: ground-truth visible masks and object names (measures the 3D part alone). Returns
    per-stage statistics."""
    t = time.perf_counter()
    cfg = cfg or RGConfig()  # its models section names the preset of the default supervision
    if kind == "oracle":
        from ..field.oracle import oracle_supervision

        if not scene.objects:
            raise ValueError(f"{scene.root}: oracle supervision needs ground-truth objects (objects.json)")
        sset = oracle_supervision(mapper, scene.train, scene.objects, text_encoder)
    elif kind == "default":  # the configured preset's models ("offline": RGB-D masks + ConSE)
        from ..models import make_perception
        from ..perception.supervision import supervise_map_multiview

        sset, stats = supervise_map_multiview(mapper, *make_perception(cfg.models.preset, cfg.models),
                                              progress, cfg.models.views_per_object)
        sset.pca.fit_now()
        return {**sset.stats(), "multiview": stats, "seconds": round(time.perf_counter() - t, 3)}
    else:
        raise ValueError(f"supervision must be 'default' or 'oracle', got {kind!r}")
    sset.pca.fit_now()  # fewer masks than the incremental PCA waits for (one keyframe): fit on them all
    return {**sset.stats(), "seconds": round(time.perf_counter() - t, 3)}


def build_grounder(scene, cfg: RGConfig, supervision: str = "default", field_seconds: float | None = None,
                   mapper: Mapper | None = None, progress: bool = False, reasoner=None) -> tuple[Grounder, dict]:
    """Map the scene's training frames (unless `mapper` is given), supervise, train the field for
    `field_seconds` if given, else its config's budget (field.steps when > 0, else field.seconds),
    and return a Grounder plus timings (report["field"]["budget"] says which ran)."""
    from ..perception.embed import MiniLMText

    report: dict = {}
    t = time.perf_counter()
    if mapper is None:   # RGB-D frames, or the photo-only fit for a scene without depth images
        mapper, built = build_map(scene, cfg.map, cfg.photo, progress)
        report["map"] = {**mapper.stats(), "built": built}
    report["seconds_map"] = round(time.perf_counter() - t, 3)
    from ..models import make_text_encoder

    text = make_text_encoder(cfg.models.preset, cfg.models) or MiniLMText()  # the preset's embedding space
    if mapper.supervision is None or supervision == "oracle":
        report["supervision"] = supervise(mapper, scene, supervision, text, progress, cfg)
    field = getattr(mapper, "field", None) or FeatureField(mapper, cfg.field)
    if (field_seconds if field_seconds is not None else cfg.field.steps or cfg.field.seconds) > 0:
        report["field"] = field.train(seconds=field_seconds, progress=progress)
        stop = report["field"].get("stop") or {}
        if field_seconds is None and stop.get("stopped") == "seconds":  # the ceiling, not the stop test, ended it
            report["field"]["warning"] = (
                f"field: stopped at its {cfg.field.seconds:g} s ceiling (field.seconds) after {stop['steps']} steps, "
                "before its stop test converged: the answers depend on this CPU's speed and load; "
                "field.steps (rg eval --field-steps N) trains a fixed count")
            log.warning(report["field"]["warning"])
    log.info("grounding ready: %d Gaussians, %d keyframes, %d field steps", len(mapper.gaussians),
             len(mapper.keyframes), field.steps)
    names = [o.name for o in scene.objects]
    grounder = Grounder.from_map(mapper, cfg, field=field, text_encoder=text, reasoner=reasoner, scene_names=names)
    if mapper.supervision is not None:
        grounder.store_texts()  # saved with the map: a later `rg ground` embeds only its query
    return grounder, report
