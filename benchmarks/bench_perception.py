"""2D supervision figures (issue 5): mask recall@0.5 and masks / seconds per view of the offline
RGB-D generator; name top-1 of the offline ConSE embedder on ground-truth masks, per view and after
multi-view aggregation through the map, against plain ConSE (no colour term)
measured in the same run, and with the optional mirror averaging; the same on real YCB photos.

    python benchmarks/bench_perception.py [--views 20] [--seeds 1 2 3] [--json] [--no-mirror]
        [--class-text gloss both] [--record]
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

from rg_core.util import run_json_script  # noqa: E402
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import add_output_flags, finish  # noqa: E402


def to_rows(res: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: one per ConSE variant (name top-1 per view, after multi-view, on YCB)."""
    rows = []
    for k, v in res.items():
        if k.startswith("conse") and isinstance(v, dict):
            ycb = res.get(f"ycb{k[5:]}", {})
            rows.append({"variant": k, "top1_per_view_pct": round(100 * v["top1_per_view"], 1),
                         "top1_multiview_pct": round(100 * v["top1_multiview"], 1),
                         "ycb_top1_of_21_pct": round(100 * ycb["top1_among_21"], 1) if "top1_among_21" in ycb else "-"})
    m = res["masks"]
    return rows, (f"{res['scenes']}; offline RGB-D masks recall@0.5 {100 * m['recall_at_0.5']:.1f}% over {m['pairs']} "
                  f"object views, {m['masks_per_view']} masks / view, {m['seconds_per_view']} s / view")


def scene(seed: int, views: int, out: Path):
    from rg_core.config import SynthConfig
    from rg_core.io.scene import read_reasoninggd
    from rg_core.synth.generator import default_objects_dir, generate_scene

    d = out / f"scene{seed}"
    if not (d / "objects.json").exists():
        generate_scene(d, SynthConfig(views=views, width=320, height=240, objects=7, seed=seed), default_objects_dir(),
                       progress=False)
    return read_reasoninggd(d)


def top1(emb: torch.Tensor, names: list[str], truth: list[str], text) -> float:
    t = text(sorted(set(names)))
    order = sorted(set(names))
    pick = (torch.nn.functional.normalize(emb, dim=-1) @ t.T).argmax(-1)
    return float(np.mean([order[int(p)] == n for p, n in zip(pick, truth)])) if len(truth) else float("nan")


def masks_section(scenes) -> dict:
    from rg_core.perception.masks import make_mask_generator

    gen = make_mask_generator("rgbd")
    hits = total = n_masks = 0
    secs = []
    for sc in scenes:
        for f in sc.frames:
            rgb, depth, vis = f.load_rgb(), f.load_depth(), f.load_visible_mask()
            t = time.perf_counter()
            masks = gen.generate(rgb, depth, f.intrinsics.K)
            secs.append(time.perf_counter() - t)
            n_masks += len(masks)
            for o in sc.objects:
                gt = vis == o.id
                if gt.mean() < 0.005:
                    continue
                total += 1
                hits += max((float((m.mask & gt).sum() / (m.mask | gt).sum()) for m in masks), default=0.0) >= 0.5
    n_views = len(secs)
    return {"recall_at_0.5": round(hits / max(total, 1), 4), "pairs": total, "masks_per_view": round(n_masks / n_views, 2),
            "seconds_per_view": round(float(np.mean(secs)), 3)}


def conse_section(scenes, embedders: dict) -> dict:
    """Per view: ground-truth visible masks embedded with each embedder, nearest scene name.
    Multi-view: the scene mapped once, the same masks as supervision, aggregated across keyframes
    through the map (the same association for every embedder: it uses masks and scales only)."""
    from rg_core.config import MapConfig
    from rg_core.field.oracle import working_ids
    from rg_core.map.mapper import Mapper
    from rg_core.map.run import stream_frames
    from rg_core.perception.embed import mask_crop
    from rg_core.perception.multiview import aggregate_multiview
    from rg_core.perception.supervision import KeyframeSupervision, SupervisionSet

    rows = {name: {"per_view": [], "multi": [], "stats": []} for name in embedders}
    for sc in scenes:
        names = [o.name for o in sc.objects]
        by_id = {o.id: o for o in sc.objects}
        mapper = Mapper(MapConfig(final_iters=50))
        stream_frames(mapper, sc.train, progress=False)
        views = []    # (keyframe index, rgb, masks, names)
        for kf in mapper.keyframes:
            *_, ids = working_ids(sc.train[kf.index], kf.size[0])
            rgb = (kf.rgb.numpy() * 255).round().astype(np.uint8)
            ms, ns = [], []
            for oid in np.unique(ids):
                m = ids == oid
                if oid == 0 or oid not in by_id or m.mean() < 0.005:
                    continue
                ms.append(m), ns.append(by_id[int(oid)].name)
            if ms:
                views.append((kf.index, rgb, ms, ns))
        flat = [n for _, _, _, ns in views for n in ns]
        for name, embedder in embedders.items():
            text = embedder.encode_texts
            sset = SupervisionSet()
            for k, rgb, ms, ns in views:
                emb = embedder.encode_images([mask_crop(rgb, m, margin=embedder.crop_margin, fill=embedder.crop_fill)
                                              for m in ms])
                sset.add(k, KeyframeSupervision(np.stack(ms), np.ones(len(ms), np.float32), np.ones(len(ms), np.int8),
                                                np.full(len(ms), 0.05, np.float32), emb))
            mapper.supervision = sset
            before = torch.cat([sset.by_keyframe[k].embeddings for k, *_ in views])
            rows[name]["per_view"].append((top1(before, names, flat, text), len(flat)))
            rows[name]["stats"].append(aggregate_multiview(mapper, sset))
            after = torch.cat([sset.by_keyframe[k].embeddings for k, *_ in views])
            rows[name]["multi"].append((top1(after, names, flat, text), len(flat)))
    wavg = lambda rs: round(sum(a * n for a, n in rs) / max(sum(n for _, n in rs), 1), 4)
    return {name: {"top1_per_view": wavg(r["per_view"]), "top1_multiview": wavg(r["multi"]),
                   "pairs": sum(n for _, n in r["per_view"]),
                   "per_scene": [{"per_view": round(a, 3), "multiview": round(b, 3)}
                                 for (a, _), (b, _) in zip(r["per_view"], r["multi"])],
                   "association": r["stats"]} for name, r in rows.items()}


def ycb_section(embedder) -> dict:
    from rg_core.io.ycb import read_ycb
    from rg_core.perception.embed import mask_crop

    root = ROOT.parent / "shared" / "data" / "rgbd" / "ycb_video_3"
    if not root.is_dir():
        return {"skipped": f"{root} missing"}
    classes, frames = read_ycb(root)
    crops, truth = [], []
    for f in frames:
        for c in f.class_ids:
            m = f.label == c
            if m.sum() >= 100:
                crops.append(mask_crop(f.rgb, m, margin=embedder.crop_margin, fill=embedder.crop_fill))
                truth.append(classes[c - 1])
    emb = embedder.encode_images(crops)
    return {"top1_among_21": round(top1(emb, classes, truth, embedder.encode_texts), 4), "pairs": len(truth)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--out", default=str(ROOT / "bench_out" / "perception"))
    add_output_flags(ap)
    ap.add_argument("--no-mirror", action="store_true", help="leave out the mirror-averaging variant (half the time)")
    ap.add_argument("--class-text", nargs="*", default=["gloss", "both"], choices=["gloss", "both"],
                    help="ConSE variants whose ImageNet classes are embedded by WordNet knowledge text")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    from rg_core.perception.embed import make_embedder

    scenes = [scene(s, a.views, out) for s in a.seeds]
    embedder = make_embedder("conse")
    # Baseline in the same run: plain ConSE (no colour term); and the optional mirror averaging.
    plain = make_embedder("conse", colour_weight=0.0)
    variants = {"conse": embedder, "conse_plain": plain}
    if not a.no_mirror:
        variants["conse_mirror"] = make_embedder("conse", mirror=True)
    # Issue 15: ImageNet classes embedded by their WordNet knowledge text (and name + gloss).
    for ct in a.class_text:
        variants[f"conse_{ct}"] = make_embedder("conse", class_text=ct)
    t = time.perf_counter()
    conse = conse_section(scenes, variants)
    res = {"scenes": f"{len(scenes)} x {a.views} views, 320x240, 7 objects, seeds {a.seeds}",
           "masks": masks_section(scenes), **conse, "seconds_conse_section": round(time.perf_counter() - t, 1),
           **{f"ycb{k[5:]}": ycb_section(e) for k, e in variants.items()}}
    print(json.dumps(res, indent=None if a.json else 1))
    a.json = False   # printed above
    return finish(a, res, "bench_perception", to_rows)


if __name__ == "__main__":
    run_json_script(main)
