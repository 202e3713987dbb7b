"""`rg demo`: the main job, from a synthetic scene to two grounded answers with pictures."""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

from ..config import RGConfig
from ..grounding.build import build_grounder
from ..io.captures import read_scene
from ..io.scene import depth_or_none
from ..map.store import save_map
from ..synth.generator import default_objects_dir, generate_scene
from ..viz.contact_sheet import write_contact_sheet
from ..viz.grounding import mask_summary, write_grounding_pngs

log = logging.getLogger(__name__)


def run_demo(cfg: RGConfig, out: Path, progress: bool = True) -> dict:
    """The main job (`rg demo`): a synthetic scene and its contact sheet; with demo.ground, its map and
    one explicit and one implicit answer with pictures. Returns the summary `rg demo` prints."""
    d = cfg.demo
    s = dataclasses.replace(cfg.synth, views=d.views, width=d.width, height=d.height, objects=d.objects,
                            seed=d.seed)
    t0 = time.perf_counter()
    summary = generate_scene(out / "scene", s, default_objects_dir(), progress=progress)
    t1 = time.perf_counter()
    scene = read_scene(out / "scene")
    sheet = write_contact_sheet(scene, out / "contact_sheet.png", d.sheet_views)
    t2 = time.perf_counter()
    result = {"scene": summary, "contact_sheet": str(sheet),
              "seconds": {"synth": round(t1 - t0, 3), "contact_sheet": round(t2 - t1, 3)}}
    if d.ground and scene.queries:
        grounder, report = build_grounder(scene, cfg, d.supervision, d.field_seconds or None, progress=progress)
        result["map"] = str(save_map(grounder.mapper, out / "scene.rgmap"))
        q = scene.queries[0]
        answers = {}
        for kind, text in (("explicit", q.explicit), ("implicit", q.implicit[0] if q.implicit else q.explicit)):
            res = grounder.ground(text, mode=kind)
            a = res.to_json()
            a["expected"] = next((o.name for o in scene.objects if o.id == q.object_id), "")
            if res.success:
                f = scene.test[0] if scene.test else scene.train[0]
                W, H = f.intrinsics.width, f.intrinsics.height
                depth, rgb = depth_or_none(f), f.load_rgb()   # the visible mask follows the view, as the node's does
                amodal, visible = grounder.masks(res, f.intrinsics.K, f.cam_to_world, W, H, depth, rgb)
                a["masks"] = mask_summary(amodal, visible, depth, rgb)
                a["pictures"] = write_grounding_pngs(grounder, res, f.intrinsics.K, f.cam_to_world, W, H, amodal,
                                                     visible, out / f"answer_{kind}")
            log.info("%s: %r -> %s (%s)", kind, text, res.target or "-", "ok" if res.success else res.message)
            answers[kind] = a
        result["answers"] = answers
        result["seconds"]["build"] = report.get("seconds_map", 0.0)
        result["seconds"]["total"] = round(time.perf_counter() - t0, 3)
    return result
