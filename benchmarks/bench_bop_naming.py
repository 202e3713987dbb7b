"""Name top-1 of the offline ConSE embedder on a BOP scene's ground-truth visible masks (issue 19):
every image, every object with >= 100 visible pixels, among the scene's names and among BOP's 21
YCB-V names (the same measure as bench_perception.py's YCB-Video section).

    python benchmarks/bench_bop_naming.py [SCENE] [--record] (default ../shared/data/rgbd/ycbv_0002_bop)
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import finish  # noqa: E402


def to_rows(res: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: top-1 per object among the scene's names, then both overall figures."""
    rows = [{"names": "scene's 6", "object": n, "top1_pct": round(100 * v, 1)}
            for n, v in res["per_object_among_scene"].items()]
    rows.append({"names": "scene's 6", "object": "all", "top1_pct": round(100 * res["top1_among_scene"], 1)})
    rows.append({"names": "YCB-V 21", "object": "all", "top1_pct": round(100 * res["top1_among_ycbv_21"], 1)})
    return rows, (f"offline ConSE on {res['pairs']} ground-truth visible masks of {Path(res['scene']).name} "
                  f"(>= 100 px); {res['seconds_per_crop']} s per crop")


def top1_picks(emb: torch.Tensor, names: list[str], text) -> list[str]:
    order = sorted(set(names))
    pick = (torch.nn.functional.normalize(emb, dim=-1) @ text(order).T).argmax(-1)
    return [order[int(p)] for p in pick]


def main(argv=None) -> int:
    from rg_core.io.bop import YCBV_NAMES, read_bop, ycb_name
    from rg_core.perception.embed import make_embedder, mask_crop

    argv = sys.argv[1:] if argv is None else argv
    record = "--record" in argv
    argv = [a for a in argv if a != "--record"]
    root = Path(argv[0]) if argv else ROOT.parent / "shared" / "data" / "rgbd" / "ycbv_0002_bop"
    torch.set_num_threads(1)
    scene = read_bop(root)
    emb_model = make_embedder("conse")
    crops, truth = [], []
    for f in scene.frames:
        rgb, ids = f.load_rgb(), f.load_visible_mask()
        for o in scene.objects:
            m = ids == o.id
            if m.sum() >= 100:
                crops.append(mask_crop(rgb, m, margin=emb_model.crop_margin, fill=emb_model.crop_fill))
                truth.append(o.name)
    t = time.perf_counter()
    emb = emb_model.encode_images(crops)
    secs = (time.perf_counter() - t) / max(len(crops), 1)
    names = [o.name for o in scene.objects]
    p_scene = top1_picks(emb, names, emb_model.encode_texts)
    p_21 = top1_picks(emb, [ycb_name(n) for n in YCBV_NAMES], emb_model.encode_texts)
    hit = lambda picks, sel=None: round(float(np.mean([p == n for p, n in zip(picks, truth) if sel in (None, n)])), 4)
    res = {"scene": str(root), "pairs": len(truth), "top1_among_scene": hit(p_scene),
           "top1_among_ycbv_21": hit(p_21), "per_object_among_scene": {n: hit(p_scene, n) for n in sorted(set(names))},
           "seconds_per_crop": round(secs, 4)}
    print(json.dumps(res))
    return finish(argparse.Namespace(record=record), res, "bench_bop_naming", to_rows)


if __name__ == "__main__":
    sys.exit(main())
