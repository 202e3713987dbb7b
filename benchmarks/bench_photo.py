"""Maps from photos without depth (issue 63): the photo-only 3DGS fit (rg_core/map/photo_fit.py) against
the RGB-D map of the same views, in the same run, on scenes nobody tuned to.

    python benchmarks/bench_photo.py [--seeds 801 802] [--views 20] [--ycbv ../shared/data/rgbd/ycbv_0002_bop]
                                     [--big-views 100] [--big-seed 803] [--big-iters 3000] [--skip-big] [--rss-gaussians 300000]
                                     [--skip-rss] [--photo-iters N] [--points 1500] [--supervision oracle]
                                     [--work DIR] [--out DIR] [--json] [--record]

Scenes: `rg synth` table tops (--seeds; 320x240, --views views, 7 objects, 3 sharing a category, as
bench_relations makes them) and the real YCB-Video scene in BOP layout (17 train / 3 test views).
Depth is withheld in memory: the scene is read as it is (poses, masks, objects, queries), then every
frame's depth_path is set to None, which is what the readers give for a photo-only layout (a ReasoningGD
folder without depth_file_path, nerfstudio, COLMAP); the synthetic scenes' points3d.ply is thinned to
--points points (a seeded sample, a sparse cloud's size, as tests/conftest.photos_only does), and the
BOP scene has no point cloud, so its fit starts from points triangulated at its poses (pycolmap,
io/sfm.triangulate_posed; photo.init_random points around the viewing distance if that finds none).
Each scene is built twice with build_grounder(scene, cfg, --supervision) (default: "oracle", ground-truth
masks and names, so the map is what differs), once with depth (the RGB-D stream + refinement) and once
without (build_map picks the photo fit), then scored on the same RGB-D test frames:
- test-view PSNR (eval/mapping.evaluate_views, whole image over the learnt background) and, for the
  photo map, its rendered depth against the sensor's (median abs error where it is opaque);
- explicit and implicit visible mIoU (eval/grounding.evaluate_queries, rendered masks);
- wall seconds of each build, per phase (map or photo fit, supervision, field), and the ratio.
--big-views: one more synthetic scene (--big-seed, 320x240) of that many views, built both ways the
same: the time to a queryable field (photo fit + supervision + field) against the 15 min target.
--rss-gaussians N: a subprocess fits the first scene's photos with max_gaussians = N, forced to grow
there (N/2 random initial Gaussians, a threshold that clones or splits all at step 10); its peak RSS
(VmHWM) and the Gaussians reached. A step profile (render forward/backward, SSIM forward/backward at
the first scene's fitted Gaussians) says where the fit's time goes.
Every fit runs at the config's own step ceiling (photo_fit.step_ceiling: 35 steps a training view
within 1000-7000: 1000 on the 20-view scenes' 17, 3045 on the 100-view scene's 87) unless --photo-iters N sets photo.iters
(and turns the per-view rule off) for all fits, or --big-iters N for the big scene alone.
Targets: PSNR within 1.5 dB, explicit mIoU within 5 points of the RGB-D figure, the big scene queryable
in <= 900 s, peak RSS <= 3 GB at 300k Gaussians. Writes photo.png (held-out PSNR against seconds of
every fit, test PSNR and mIoU bars) and photo.json to --out.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import gc
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import add_output_flags, finish, pyplot, save_figure  # noqa: E402

PSNR_GAP_DB, MIOU_GAP, BIG_LIMIT_S, RSS_LIMIT_GB = 1.5, 5.0, 900.0, 3.0


# ------------------------------------------------------------------------------ scenes

def make_scenes(args, work: Path) -> list[tuple[str, Path, str]]:
    """[(key, folder, kind)], kind "table", "big" or "real"; synthetic ones made in `work` unless there."""
    from bench_relations import make_scene

    out = []
    for seed in args.seeds:
        d = make_scene(work / f"seed_{seed}_{args.views}", seed, SimpleNamespace(views=args.views, objects=7, same_category=3))
        out.append((f"seed_{seed}", d, "table"))
    if args.ycbv != "none" and Path(args.ycbv).is_dir():
        out.append((Path(args.ycbv).name.replace("-", "_").lower(), Path(args.ycbv), "real"))
    elif args.ycbv != "none":
        print(f"bench_photo: {args.ycbv} is missing: the real scene is skipped", file=sys.stderr)
    if not args.skip_big and args.big_views > 0:
        d = make_scene(work / f"seed_{args.big_seed}_{args.big_views}", args.big_seed,
                       SimpleNamespace(views=args.big_views, objects=7, same_category=3))
        out.append((f"big_{args.big_seed}_{args.big_views}v", d, "big"))
    return out


def withhold_depth(scene, points: int, seed: int = 0):
    """A copy of `scene` as a photo-only reader gives it: no frame has a depth image; its sparse points
    (if any) thinned to `points` (seeded; 0: none, random initialisation)."""
    from rg_core.io.scene import SparsePoints

    pts = scene.load_points()
    s = copy.deepcopy(scene)
    for f in s.train + s.test:
        f.depth_path = None
    s.points, s.points_path = None, None
    if pts is not None and points > 0 and len(pts.xyz) >= 4:
        sel = np.random.default_rng(seed).choice(len(pts.xyz), min(points, len(pts.xyz)), replace=False)
        s.points = SparsePoints(np.asarray(pts.xyz)[sel], np.asarray(pts.rgb)[sel], f"{pts.source}: {len(sel)} of {len(pts.xyz)}")
    return s


# ------------------------------------------------------------------------------ one build

def build_and_score(scene, score_scene, cfg, supervision: str) -> tuple[dict, object]:
    """build_grounder on `scene`, scored on `score_scene`'s test frames (the RGB-D ones) -> (figures, mapper)."""
    from rg_core.eval.grounding import evaluate_queries
    from rg_core.eval.mapping import evaluate_views
    from rg_core.grounding.build import build_grounder

    t = time.perf_counter()
    g, rep = build_grounder(scene, cfg, supervision)
    wall = time.perf_counter() - t
    field = rep.get("field") or {}
    R = {"build_s": round(wall, 1), "map_s": round(rep["seconds_map"], 1),
         "supervision_s": round((rep.get("supervision") or {}).get("seconds", 0.0), 1),
         "field_s": round(field.get("seconds", 0.0), 1), "field_steps": int(field.get("steps", 0)),
         "field_stop": (field.get("stop") or {}).get("stopped", "-"),
         "keyframes": len(g.mapper.keyframes), "gaussians": len(g.mapper.gaussians)}
    t = time.perf_counter()
    ev = evaluate_views(g.mapper, score_scene.test)
    R["psnr_db"] = round(ev["psnr"], 2)
    R["depth_error_median_mm"] = round(1000 * ev["depth_abs_error_median_m"], 1)
    R["coverage"] = ev["coverage"]
    q = evaluate_queries(g, scene, 1)
    R["explicit_miou"] = q["explicit"]["miou_visible"]
    R["implicit_miou"] = q["implicit"].get("miou_visible", float("nan"))
    R["eval_s"] = round(time.perf_counter() - t, 1)
    built = (rep.get("map") or {}).get("built") or {}
    if built.get("kind") == "photo":
        p = built["photo"]
        R.update(fit_init=p.get("init", ""), fit_steps=p["steps"], fit_ceiling=p["ceiling"], fit_stopped=p["stopped"], fit_s=round(p["seconds"], 1), cloned=p["cloned"],
                 split=p["split"], pruned=p["pruned"], curve=p["heldout_psnr"],
                 heldout_psnr_db=round(p["heldout_psnr"][-1][2], 2) if p["heldout_psnr"] else float("nan"),
                 s_per_step=round(p["seconds"] / max(p["steps"], 1), 3))
        R["fit_other_s"] = round(R["map_s"] - R["fit_s"], 1)   # views loaded, keyframes' rendered depth
    mapper = g.mapper
    del g
    return R, mapper


def step_profile(mapper, scene, cfg, n: int = 8) -> dict:
    """Seconds of one photo-fit step's parts at this map's Gaussians, on the first training view:
    render forward, its backward (L1), SSIM forward and backward (what photo_fit.step runs)."""
    import torch

    from rg_core.map.frames import map_camera
    from rg_core.map.photo_fit import photo_view
    from rg_core.map.photo_losses import ssim
    from rg_core.render.rasterize import rasterize

    v = photo_view(scene.train[0], cfg.map.width)
    h, w = v.rgb.shape[:2]
    cam = map_camera(cfg.map, v.K, v.cam_to_world, w, h)
    g = mapper.gaussians
    T = {"render_fwd": 0.0, "render_bwd": 0.0, "ssim_fwd": 0.0, "ssim_bwd": 0.0}
    for _ in range(n):
        ps = {k: t.detach().requires_grad_(True) for k, t in g.tensors().items()}
        t0 = time.perf_counter()
        out = rasterize(ps["means"], torch.exp(ps["log_scales"]), ps["quats"], torch.sigmoid(ps["opacity_logits"]),
                        ps["colors"], cam, antialiased=cfg.map.antialiased)
        t1 = time.perf_counter()
        (out.channels - v.rgb).abs().mean().backward()
        t2 = time.perf_counter()
        img = out.channels.detach().clone().requires_grad_(True)
        s = ssim(img, v.rgb)
        t3 = time.perf_counter()
        (1 - s).backward()
        t4 = time.perf_counter()
        for k, dt in zip(T, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            T[k] += dt / n
    return {f"{k}_ms": round(1000 * v, 1) for k, v in T.items()} | {"gaussians": len(g), "size": f"{w}x{h}"}


def run_scene(key: str, path: Path, kind: str, args, profile: bool) -> dict:
    from rg_core.config import RGConfig
    from rg_core.io.captures import read_scene

    cfg = RGConfig()
    iters = args.big_iters if kind == "big" and args.big_iters else args.photo_iters
    if iters:
        cfg.photo = dataclasses.replace(cfg.photo, iters=iters, steps_per_view=0)
    for kv in args.photo_set or ():
        k, _, v = kv.partition("=")
        cfg.photo = dataclasses.replace(cfg.photo, **{k: type(getattr(cfg.photo, k))(v)})
    sup = args.supervision
    rgbd = read_scene(path)
    photo = withhold_depth(rgbd, args.points)
    R: dict = {"scene": key, "kind": kind, "train_views": len(rgbd.train), "test_views": len(rgbd.test),
               "objects": len(rgbd.objects), "init": f"{len(photo.points.xyz)} points" if photo.points is not None
               else "no points: triangulated at the poses, else random"}
    t0 = time.perf_counter()
    r, m = build_and_score(rgbd, rgbd, cfg, sup)
    R["rgbd"] = r
    del m
    gc.collect()
    print(f"bench_photo {key}: RGB-D build {r['build_s']} s, PSNR {r['psnr_db']}, explicit {r['explicit_miou']}",
          file=sys.stderr)
    p, m = build_and_score(photo, rgbd, cfg, sup)
    R["photo"] = p
    print(f"bench_photo {key}: photo build {p['build_s']} s (fit {p['fit_s']} s, {p['fit_steps']} steps, {p['fit_stopped']}), "
          f"PSNR {p['psnr_db']}, explicit {p['explicit_miou']}", file=sys.stderr)
    if profile:
        R["step_profile"] = step_profile(m, photo, cfg)
        print(f"bench_photo {key}: step profile {R['step_profile']}", file=sys.stderr)
    del m
    gc.collect()
    R["psnr_gap_db"] = round(p["psnr_db"] - r["psnr_db"], 2)
    R["explicit_gap"] = round(p["explicit_miou"] - r["explicit_miou"], 2)
    R["implicit_gap"] = round(p["implicit_miou"] - r["implicit_miou"], 2)
    R["queryable_s"] = round(p["map_s"] + p["supervision_s"] + p["field_s"], 1)   # photo fit + supervision + field
    R["rgbd_queryable_s"] = round(r["map_s"] + r["supervision_s"] + r["field_s"], 1)
    R["time_ratio"] = round(R["queryable_s"] / max(R["rgbd_queryable_s"], 1e-9), 1)
    R["wall_s"] = round(time.perf_counter() - t0, 1)
    return R


# ------------------------------------------------------------------------------ peak RSS

def peak_rss_gb() -> float:
    """This process's peak resident set (VmHWM: its own, unlike getrusage's ru_maxrss, which a child
    inherits from the parent it was forked from and keeps across exec)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 1e9   # kB (KiB) -> GB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9   # KiB on Linux


def rss_worker(scene_dir: str, n: int) -> dict:
    """In its own process: the scene's photos fitted with max_gaussians = n, grown there at step 10."""
    from rg_core.config import MapConfig, PhotoMapConfig
    from rg_core.io.captures import read_scene
    from rg_core.map.photo_fit import photo_mapper

    scene = withhold_depth(read_scene(scene_dir), 0)
    start = peak_rss_gb()
    pc = PhotoMapConfig(iters=30, init_random=n // 2, triangulate=False, densify_from=10, densify_every=10, densify_until=1.0,
                        grad_threshold=1e-12, reset_opacity_every=0, check_every=15, converge_db=0.0)
    t = time.perf_counter()
    m, fit = photo_mapper(scene.train, MapConfig(max_gaussians=n), pc, None, progress=False)
    return {"peak_rss_gb": round(peak_rss_gb(), 3),
            "start_rss_gb": round(start, 3), "gaussians_max": max(h[3] for h in fit.history),
            "gaussians_final": len(m.gaussians), "steps": fit.steps, "seconds": round(time.perf_counter() - t, 1),
            "keyframes": len(m.keyframes), "cloned": fit.totals["cloned"], "split": fit.totals["split"]}


def measure_rss(scene_dir: Path, n: int) -> dict:
    res = subprocess.run([sys.executable, __file__, "--rss-worker", str(scene_dir), str(n)], capture_output=True,
                         text=True, timeout=3600)
    if res.returncode != 0:
        raise RuntimeError(f"RSS worker failed ({res.returncode}): {res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------ report

def _get(s: dict, path: str):
    v = s
    for k in path.split("."):
        if not isinstance(v, dict) or k not in v:
            return None
        v = v[k]
    return v


# (path in a scene's record, label, target test or None, target text, scene kinds it applies to or None)
FIGURES = [
    ("rgbd.psnr_db", "test PSNR (dB), RGB-D map", None, "", None),
    ("photo.psnr_db", "test PSNR (dB), photo map", None, "", None),
    ("psnr_gap_db", "PSNR: photo - RGB-D (dB)", lambda v: v >= -PSNR_GAP_DB, f">= -{PSNR_GAP_DB}", None),
    ("photo.heldout_psnr_db", "photo fit: held-out views' PSNR, decision (dB)", None, "", None),
    ("photo.depth_error_median_mm", "photo map depth vs sensor, median (mm)", None, "", None),
    ("rgbd.explicit_miou", "explicit visible mIoU, RGB-D", None, "", None),
    ("photo.explicit_miou", "explicit visible mIoU, photo", None, "", None),
    ("explicit_gap", "explicit: photo - RGB-D (points)", lambda v: v >= -MIOU_GAP, f">= -{MIOU_GAP:g}", None),
    ("rgbd.implicit_miou", "implicit visible mIoU, RGB-D", None, "", None),
    ("photo.implicit_miou", "implicit visible mIoU, photo", None, "", None),
    ("rgbd_queryable_s", "RGB-D: map + supervision + field (s)", None, "", None),
    ("queryable_s", "photo: fit + supervision + field (s)", lambda v: v <= BIG_LIMIT_S, f"<= {BIG_LIMIT_S:g}", {"big"}),
    ("time_ratio", "time to queryable: photo / RGB-D", None, "", None),
    ("photo.fit_s", "photo fit (s)", None, "", None),
    ("photo.fit_other_s", "photo map: views, rendered depth (s)", None, "", None),
    ("photo.supervision_s", "photo: supervision (s)", None, "", None),
    ("photo.field_s", "photo: field (s)", None, "", None),
    ("rgbd.map_s", "RGB-D: map (s)", None, "", None),
    ("rgbd.supervision_s", "RGB-D: supervision (s)", None, "", None),
    ("rgbd.field_s", "RGB-D: field (s)", None, "", None),
    ("photo.fit_steps", "photo fit: steps", None, "", None),
    ("photo.fit_stopped", "photo fit: stopped by", None, "", None),
    ("photo.s_per_step", "photo fit: seconds a step", None, "", None),
    ("photo.gaussians", "Gaussians, photo map", None, "", None),
    ("rgbd.gaussians", "Gaussians, RGB-D map", None, "", None),
    ("photo.keyframes", "keyframes, photo map", None, "", None),
    ("rgbd.keyframes", "keyframes, RGB-D map", None, "", None),
    ("step_profile.render_fwd_ms", "step profile: render forward (ms)", None, "", None),
    ("step_profile.render_bwd_ms", "step profile: render backward (ms)", None, "", None),
    ("step_profile.ssim_fwd_ms", "step profile: SSIM forward (ms)", None, "", None),
    ("step_profile.ssim_bwd_ms", "step profile: SSIM backward (ms)", None, "", None),
    ("rss.peak_rss_gb", "peak RSS of a fit (GB)", lambda v: v <= RSS_LIMIT_GB, f"<= {RSS_LIMIT_GB:g}", None),
    ("rss.gaussians_max", "Gaussians reached in that fit", None, "", None),
]


def table(report: dict) -> list[dict]:
    scenes = report["scenes"]
    rows = []
    for path, label, test, target, kinds in FIGURES:
        vals = {s["scene"]: _get(s, path) if kinds is None or s.get("kind") in kinds else None for s in scenes}
        if all(v is None for v in vals.values()):
            continue
        row = {"figure": label}
        for s, v in vals.items():
            row[s] = "-" if v is None or (isinstance(v, float) and v != v) else v
        row["target"] = target or "-"
        got = [v for v in vals.values() if isinstance(v, (int, float)) and v == v]
        row["met"] = ("-" if test is None or not got else
                      "yes" if all(test(v) for v in got) else f"no ({sum(not test(v) for v in got)} of {len(got)})")
        rows.append(row)
    return rows


def print_table(rows: list[dict], file=None) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    w = {k: max(len(k), *(len(str(r.get(k, ""))) for r in rows)) for k in keys}
    print("  ".join(k.ljust(w[k]) for k in keys), file=file)
    for r in rows:
        print("  ".join(str(r.get(k, "")).ljust(w[k]) for k in keys), file=file)


def to_rows(report: dict) -> tuple[list[dict], str]:
    sc = [s for s in report["scenes"] if "error" not in s]
    iters = [s["photo"]["fit_ceiling"] for s in sc]
    rule = f"photo.iters {report['photo_iters']}" if report["photo_iters"] else "config: 35 a view, 1000-7000"
    errs = [f"{s['scene']} failed" for s in report["scenes"] if "error" in s]
    big = "no big scene" if report["skip_big"] else f"big: seed {report['big_seed']}, {report['big_views']} views"
    notes = (f"{report['supervision']} supervision; synth seeds {' '.join(map(str, report['seeds'])) or 'none'} "
             f"({report['views']} views, 320x240, 7 objects), {report['ycbv']}, "
             f"{big}; "
             f"depth withheld (synthetic: {report['points']} sparse points, BOP: triangulated); photo fit "
             f"ceiling {'/'.join(map(str, iters))} steps ({rule}); "
             f"PSNR on the RGB-D test frames; RSS: {report.get('rss_note', 'not run')}"
             f"{'; ' + ', '.join(errs) if errs else ''}; wall {report['wall_s']:.0f} s")
    return table(report), notes


def plot(report: dict, png: Path) -> Path:
    plt = pyplot()
    sc = [s for s in report["scenes"] if "error" not in s]
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8), gridspec_kw={"width_ratios": [1.6, 1, 1]})
    ax = axes[0]
    for i, s in enumerate(sc):
        c = f"C{i}"
        cur = np.asarray(s["photo"].get("curve") or [[0, 0, np.nan, 0]], float)
        ax.plot(cur[:, 1], cur[:, 2], "-o", ms=2.5, color=c, label=f"{s['scene']} photo fit (held-out views)")
        ax.axhline(s["rgbd"]["psnr_db"], color=c, ls="--", lw=0.8)
    ax.set_xlabel("seconds of the photo fit")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title("photo fit: held-out PSNR against time (dashed: RGB-D map, test views)", fontsize=8)
    ax.legend(fontsize=6)
    x = np.arange(len(sc))
    for ax, key, label in ((axes[1], "psnr_db", "test-view PSNR (dB)"), (axes[2], "explicit_miou", "explicit visible mIoU")):
        for j, kind in enumerate(("rgbd", "photo")):
            vals = [s[kind][key] for s in sc]
            ax.bar(x + (j - 0.5) * 0.38, vals, 0.38, label="RGB-D" if kind == "rgbd" else "photos only")
            for i, v in enumerate(vals):
                ax.text(i + (j - 0.5) * 0.38, v, f"{v:.1f}", ha="center", va="bottom", fontsize=6)
        ax.set_xticks(x, [s["scene"] for s in sc], fontsize=6, rotation=15)
        ax.set_ylabel(label)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle("maps from photos without depth against RGB-D maps of the same views", fontsize=9)
    save_figure(fig, png)
    return png


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == "--rss-worker":
        print(json.dumps(rss_worker(sys.argv[2], int(sys.argv[3]))))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[801, 802], help="rg synth table-top seeds")
    ap.add_argument("--views", type=int, default=20, help="views of each table-top scene")
    ap.add_argument("--ycbv", default=str(ROOT.parent / "shared" / "data" / "rgbd" / "ycbv_0002_bop"),
                    help='a YCB-Video scene in BOP layout ("none": skip)')
    ap.add_argument("--big-views", type=int, default=100, help="views of the time-to-queryable scene")
    ap.add_argument("--big-seed", type=int, default=803)
    ap.add_argument("--big-iters", type=int, default=0,
                    help="the big scene's photo.iters, per-view rule off (0: as --photo-iters)")
    ap.add_argument("--skip-big", action="store_true", help="no time-to-queryable scene")
    ap.add_argument("--rss-gaussians", type=int, default=300000, help="max_gaussians of the peak-RSS fit (0: skip)")
    ap.add_argument("--skip-rss", action="store_true")
    ap.add_argument("--photo-iters", type=int, default=0,
                    help="photo.iters of every fit, per-view rule off (0: the config's step ceiling, 35 steps a view "
                         "within 1000-7000; the default run takes 20-40 min on 2 cores)")
    ap.add_argument("--photo-set", action="append", metavar="KEY=VALUE",
                    help="a photo-fit setting of every photo build (config photo.KEY), e.g. depth_smoothness=0.1")
    ap.add_argument("--points", type=int, default=1500, help="sparse points kept of a synthetic scene's points3d.ply")
    ap.add_argument("--supervision", default="oracle", choices=("oracle", "default"))
    ap.add_argument("--work", help="keep scenes here (default: a temporary folder)")
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    t0 = time.perf_counter()
    report = {"seeds": args.seeds, "views": args.views, "big_views": args.big_views, "big_seed": args.big_seed,
              "skip_big": bool(args.skip_big or args.big_views <= 0), "photo_iters": args.photo_iters,
              "points": args.points, "supervision": args.supervision,
              "ycbv": Path(args.ycbv).name if args.ycbv != "none" else "no real scene"}
    with tempfile.TemporaryDirectory(prefix="bench_photo ") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        scenes = make_scenes(args, work)
        rss = None
        if args.rss_gaussians > 0 and not args.skip_rss and scenes:   # first: its own process, a quiet start
            key, path, _ = scenes[0]
            try:
                rss = measure_rss(path, args.rss_gaussians)
                rss["scene"] = key
                report["rss_note"] = (f"{key}'s photos, grown to max_gaussians at step 10 of {rss['steps']}, own process "
                                      f"(start {rss['start_rss_gb']} GB)")
                print(f"bench_photo: RSS {rss}", file=sys.stderr)
            except Exception as exc:  # noqa: BLE001
                report["rss_note"] = f"failed: {type(exc).__name__}"
                print(f"bench_photo: RSS worker failed: {exc}", file=sys.stderr)
        results = []
        for i, (key, path, kind) in enumerate(scenes):
            try:
                r = run_scene(key, path, kind, args, profile=i == 0)
            except Exception as exc:  # noqa: BLE001 - one scene failing keeps the others' figures
                import traceback

                traceback.print_exc()
                r = {"scene": key, "kind": kind, "error": f"{type(exc).__name__}: {exc}"[:500]}
            print(json.dumps({k: v for k, v in r.items() if k not in ("photo", "rgbd")}), file=sys.stderr)
            results.append(r)
        if rss is not None:
            rec = next((r for r in results if r["scene"] == rss["scene"]), None)
            if rec is not None:
                rec["rss"] = rss
    report["scenes"] = results
    report["wall_s"] = round(time.perf_counter() - t0, 1)
    rows = table(report)
    print_table(rows, sys.stderr if args.json else sys.stdout)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    png = plot(report, out / "photo.png")
    (out / "photo.json").write_text(json.dumps(report, indent=1, default=str))
    return finish(args, report, "bench_photo", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
