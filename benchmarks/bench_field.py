"""Feature field: oracle-supervised error against training time on a synthetic scene.

    python benchmarks/bench_field.py [--scene DIR] [--budgets 1 2 3 5 8 13 20 40 80] [--out DIR] [--json] [--record]

Without --scene it generates a 40-view 320x240 scene with 7 objects (seed 0) with `rg synth`'s
generator, maps it with the default MapConfig (`map_scene`), builds oracle supervision (ground-
truth visible masks, object names embedded with the packaged MiniLM text model) and, for each
budget, trains a fresh field (default FieldConfig) for that many seconds and runs the two checks
of rg_core.field.oracle on the test views; then once more with the default stop test (marked). Writes OUT/field_error_vs_time.png and OUT/field.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import torch  # noqa: E402

from rg_core.config import FieldConfig, MapConfig, SynthConfig  # noqa: E402
from rg_core.field import FeatureField  # noqa: E402
from rg_core.field.oracle import RandomNameEmbedding, oracle_checks, oracle_supervision  # noqa: E402
from rg_core.io.captures import read_scene  # noqa: E402
from rg_core.eval.mapping import map_scene  # noqa: E402
from rg_core.synth.generator import default_objects_dir, generate_scene  # noqa: E402
from rg_core.util import peak_rss_mb  # noqa: E402
from _common import add_output_flags, finish, pyplot, save_figure  # noqa: E402


def to_rows(report: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: one per training budget."""
    rows = [{"budget_s": r["budget_s"], "trained_s": r["seconds"], "steps": r["steps"],
             "argmax_in_mask_pct": round(100 * r["argmax_in_mask"], 1),
             "instance_separation_pct": round(100 * r["instance_separation"], 1)} for r in report["budgets"]]
    m = report["map"]
    return rows, (f"40 views 320x240, 7 objects, oracle supervision ({report['names']}), {report['threads']} torch "
                  f"thread(s); map {m['keyframes']} keyframes, {m['gaussians']} Gaussians; the default trains until "
                  f"the stop test (ceiling {report['default_seconds']:g} s); peak RSS {report['peak_rss_mb']:.0f} MB")


def plot(rows: list[dict], default_budget: float, out_png: Path) -> None:
    plt = pyplot()
    from matplotlib.ticker import FuncFormatter, NullFormatter

    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.axhline(90, color="grey", lw=0.8, ls="--")
    fixed = [r for r in rows if r["budget_s"] != "stop test"]
    secs = [r["seconds"] for r in fixed]
    ax.plot(secs, [100 * r["argmax_in_mask"] for r in fixed], "o-", label="relevancy argmax in mask (3x3 peak)")
    ax.plot(secs, [100 * r["argmax_in_mask_raw"] for r in fixed], "s:", label="relevancy argmax in mask (raw pixel)")
    ax.plot(secs, [100 * r["instance_separation"] for r in fixed], "^--", label="instance separation (pixels)")
    for r in rows:
        if r["budget_s"] == "stop test":  # the default: trained until the held-out accuracy converged
            for k in ("argmax_in_mask", "instance_separation"):
                ax.plot([r["seconds"]], [100 * r[k]], "o", ms=11, mfc="none", mec="red", mew=1.5)
            ax.annotate(f"stop test (default): {r['steps']} steps", (r["seconds"], 100 * r["instance_separation"]),
                        textcoords="offset points", xytext=(6, -14), fontsize=7, color="red")
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("feature training time (s)")
    ax.set_ylabel("% on test views")
    ax.set_ylim(0, 102)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("Feature field with oracle supervision: error against run time", fontsize=9)
    save_figure(fig, out_png)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="scene folder (default: generate 40 views 320x240, 7 objects)")
    ap.add_argument("--budgets", type=float, nargs="+", default=[1, 2, 3, 5, 8, 13, 20, 40, 80])
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (1 is fastest on 2 shared cores)")
    ap.add_argument("--random-names", action="store_true", help="random name vectors instead of MiniLM")
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    if len(args.budgets) < 4:
        ap.error("give at least four budgets")
    torch.set_num_threads(args.threads)
    default_cfg = FieldConfig()
    report = {"default_seconds": default_cfg.seconds, "threads": args.threads, "budgets": []}
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = args.scene
        if scene_dir is None:
            scene_dir = str(Path(tmp) / "synth")
            t = time.perf_counter()
            generate_scene(scene_dir, SynthConfig(views=40, width=320, height=240, objects=7, seed=0),
                           default_objects_dir(), progress=False)
            print(f"generated {scene_dir} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        mapper, map_rep = map_scene(scene_dir, MapConfig(), progress=True)
        scene = read_scene(scene_dir)
        report["map"] = {k: map_rep[k] for k in ("keyframes", "gaussians", "seconds_total", "train_frames", "test_frames")}
        print(f"map: {map_rep['keyframes']} keyframes, {map_rep['gaussians']} Gaussians, "
              f"{map_rep['seconds_total']:.1f} s", file=sys.stderr)
        embed, report["names"] = RandomNameEmbedding(), "random unit vectors"
        if not args.random_names:
            try:
                from rg_core.perception.embed import MiniLMText

                embed, report["names"] = MiniLMText(), "MiniLM text embeddings"
            except Exception as exc:  # noqa: BLE001 - any loading failure: fall back, and say so
                print(f"MiniLM unavailable ({exc}); random name vectors instead", file=sys.stderr)
        oracle_supervision(mapper, scene.train, scene.objects, embed)
        report["supervision"] = mapper.supervision.stats()
        for b in list(args.budgets) + ["stop test"]:
            field = FeatureField(mapper, default_cfg)
            tr = field.train(progress=True) if b == "stop test" else field.train(seconds=b, progress=True)
            t = time.perf_counter()
            chk = oracle_checks(field, scene.test, scene.objects, embed)
            row = {"budget_s": b, "seconds": round(tr["seconds"], 2), "steps": tr["steps"],
                   "steps_per_s": round(tr["steps"] / max(tr["seconds"], 1e-9), 2),
                   "loss_language": round(tr.get("language", float("nan")), 5),
                   "loss_instance": round(tr.get("instance", float("nan")), 5),
                   "argmax_in_mask": round(chk["argmax_in_mask"], 4), "argmax_in_mask_raw": round(chk["argmax_in_mask_raw"], 4),
                   "instance_separation": round(chk["instance_separation"], 4), "pairs": chk["pairs"],
                   "pixels": chk["pixels"], "seconds_checks": round(time.perf_counter() - t, 2)}
            report["budgets"].append(row)
            print(f"budget {b} ({row['seconds']:.1f} s): {row['steps']:>4} steps, argmax in mask "
                  f"{100 * row['argmax_in_mask']:.1f}% (raw {100 * row['argmax_in_mask_raw']:.1f}%), instance separation "
                  f"{100 * row['instance_separation']:.1f}% over {row['pairs']} (object, view) pairs", file=sys.stderr)
        report["stop"] = field.stop
    report["peak_rss_mb"] = round(peak_rss_mb(), 1)
    out = Path(args.out)
    png = out / "field_error_vs_time.png"
    plot(report["budgets"], default_cfg.seconds, png)
    report["plot"] = str(png)
    (out / "field.json").write_text(json.dumps(report, indent=1))
    print(f"\n{'budget s':>8} {'steps':>6} {'argmax%':>8} {'raw%':>6} {'separation%':>12}"
          + "".join(f"\n{str(r['budget_s']):>9} {r['steps']:>6} {100 * r['argmax_in_mask']:>8.1f} "
                    f"{100 * r['argmax_in_mask_raw']:>6.1f} {100 * r['instance_separation']:>12.1f}"
                    + ("  <- default" if r["budget_s"] == "stop test" else "") for r in report["budgets"]),
          file=sys.stderr)
    print(f"plot: {png}", file=sys.stderr)
    return finish(args, report, "bench_field", to_rows, plots=[png])


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
