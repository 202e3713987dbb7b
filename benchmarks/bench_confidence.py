"""Calibrated confidence and abstention (issue 26): fit the model on some scenes, report it on others.

    python benchmarks/bench_confidence.py --fit [--seeds 101 ... 124]       # writes the model
    python benchmarks/bench_confidence.py [--seeds 201 ... 210] [--real DIR ...] [--json] [--record]

Every scene (`rg synth`, 30 views 320x240, 7 objects, each seed; and the real scenes: by default
YCB-Video 0002 in BOP layout and the YCB-Video 0000 frames of ../shared/data/rgbd) is evaluated by
`rg eval --implicit 3` with default and oracle supervision in fresh processes; each answered query
gives its evidence (rg_core/grounding/confidence.py FEATURES) and whether it is right (target right
and mean visible IoU >= 0.5). --fit fits a logistic regression on them (standardised features,
scikit-learn, its L2 strength chosen by leave-one-scene-out log-loss) and picks the abstention
threshold from their risk-coverage curve: the lowest one at which wrong answers returned as success
are at most 8 % of all answers. It writes rg_core/perception/data/confidence_offline.json.
Without --fit the stored model is reported on the scenes given (never the fit seeds): AUROC, ECE,
wrong answers returned as success (share of all answers), right answers returned, abstained right
explicit answers with oracle supervision, and the seconds a query spends on its confidence.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from rg_core.config import SynthConfig  # noqa: E402
from rg_core.eval.grounding import auroc, calibration  # noqa: E402
from rg_core.report.plots import calibration_png  # noqa: E402
from rg_core.grounding.confidence import FEATURES, ConfidenceModel, load_model, model_path  # noqa: E402
from rg_core.synth.generator import default_objects_dir, generate_scene  # noqa: E402
from _common import add_output_flags, finish  # noqa: E402

RUN = "import sys; from rg_core.cli import main; sys.exit(main(sys.argv[1:]))"
FIT_SEEDS = tuple(range(101, 125))
HELD_OUT_SEEDS = tuple(range(201, 211))
SUPERVISIONS = ("default", "oracle")   # one model each: their evidence lives on different scales
REAL = ("ycbv_0002_bop", "ycb_video_3")   # held-out real scenes (../shared/data/rgbd): never fitted on
MAX_WRONG = 0.08   # the threshold: the lowest at which the fit answers' out-of-scene wrong-returned share is at most this


def rg_eval(scene: str, supervision: str) -> dict:
    """`rg eval SCENE --supervision S --implicit 3 --json` in a fresh single-threaded process."""
    env = dict(os.environ, HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1", OMP_NUM_THREADS="1",
               PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-c", RUN, "eval", scene, "--supervision", supervision, "--implicit", "3",
                          "--json", "--quiet"], env=env, capture_output=True, text=True, timeout=3600, cwd=ROOT)
    if res.returncode != 0:
        raise RuntimeError(f"rg eval failed on {scene} ({supervision}): {res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def collect(scenes: list[tuple[str, str]], supervisions: list[str], workers: int = 2) -> list[dict]:
    """Per-query records of every scene and supervision, tagged with both."""
    jobs = [(name, path, sup) for name, path in scenes for sup in supervisions]

    def one(job):
        name, path, sup = job
        d = rg_eval(path, sup)
        print(f"{name} {sup}: {len(d['eval']['queries'])} queries, explicit visible "
              f"{d['eval']['explicit']['miou_visible']}", file=sys.stderr)
        return [{**q, "scene": name, "supervision": sup,
                 "seconds_confidence": (d["eval"]["seconds"]["stages_median"].get("confidence"))}
                for q in d["eval"]["queries"]]
    with ThreadPoolExecutor(workers) as pool:
        return [q for qs in pool.map(one, jobs) for q in qs]


def make_scenes(seeds, tmp: Path, real: list[str]) -> list[tuple[str, str]]:
    out = []
    for seed in seeds:
        d = tmp / f"synth_seed{seed}"
        generate_scene(d, SynthConfig(views=30, seed=seed), default_objects_dir(), progress=False)
        out.append((f"synth seed {seed}", str(d)))
    for r in real:
        if not Path(r).is_dir():
            raise SystemExit(f"{r}: real scene folder not found")
        out.append((Path(r).name, r))
    return out


C_GRID = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)   # inverse L2 strengths tried; leave-one-scene-out picks one


def _logistic(X: np.ndarray, y: np.ndarray, C: float):
    """-> (mean, std, fitted LogisticRegression) on features X [Q, F] with nan as the mean."""
    from sklearn.linear_model import LogisticRegression

    mean = np.nan_to_num(np.nanmean(np.where(np.isfinite(X), X, np.nan), 0)) if len(X) else np.zeros(X.shape[1])
    X = np.where(np.isfinite(X), X, mean)   # a missing value as the mean (a column never measured: 0)
    std = np.maximum(X.std(0), 1e-6)
    return mean, std, LogisticRegression(C=C, max_iter=1000).fit((X - mean) / std, y)


def choose_c(X: np.ndarray, y: np.ndarray, scenes: np.ndarray) -> tuple[float, dict, np.ndarray]:
    """The regularisation whose models, each fitted without one scene, predict that scene's answers
    best (pooled log-loss of ConfidenceModel.probabilities). -> (C, loss per C, those out-of-scene
    probabilities [Q] at C)."""
    loss, probs = {}, {}
    for C in C_GRID:
        p = np.zeros(len(y))
        for s in np.unique(scenes):
            out = scenes == s
            mean, std, lr = _logistic(X[~out], y[~out], C)
            p[out] = ConfidenceModel("", "", [""] * X.shape[1], mean, std, lr.coef_[0], float(lr.intercept_[0]), 0.5).probabilities(X[out])
        probs[C] = p
        p = np.clip(p, 1e-6, 1 - 1e-6)
        loss[C] = round(float(-np.mean(y * np.log(p) + (~y) * np.log(1 - p))), 4)
    C = min(loss, key=loss.get)
    return C, loss, probs[C]


def fit(queries: list[dict], preset: str, supervision: str, fitted_on: str,
        features: tuple[str, ...] = FEATURES) -> ConfidenceModel:
    """A logistic model on `features` of the answered queries of maps with `supervision`, its L2
    strength chosen by leave-one-scene-out log-loss (choose_c)."""
    qs = [q for q in queries if q["answered"] and q["supervision"] == supervision]
    X = np.array([[q["evidence"].get(k, np.nan) for k in features] for q in qs], np.float64)
    y = np.array([q["right"] for q in qs], bool)
    C, losses, p_out = choose_c(X, y, np.array([q["scene"] for q in qs]))
    mean, std, lr = _logistic(X, y, C)
    m = ConfidenceModel(preset, supervision, list(features), mean, std, lr.coef_[0], float(lr.intercept_[0]), 0.5,
                        f"{fitted_on}, C={C:g}")
    # the threshold from the out-of-scene probabilities: on its own fit answers a model is surer
    # than on a new scene, and a threshold read there lets more wrong answers through
    m.threshold = next((t for t in np.round(np.arange(0.0, 1.0, 0.01), 2)
                        if float(((p_out >= t) & ~y).mean()) <= MAX_WRONG), 0.99)
    p = m.probabilities(X)
    for q, pq in zip(qs, p):
        q["confidence"], q["success"] = float(pq), bool(pq >= m.threshold)
    c = calibration(qs)["all"]
    m.metrics = {**{k: c[k] for k in ("answers", "right", "auroc", "ece", "wrong_success_share", "right_returned_share")},
                 "C": C, "loso_log_loss": {f"{k:g}": v for k, v in losses.items()}}
    return m


def auroc_interval(qs: list[dict], n: int = 1000, seed: int = 0) -> list[float]:
    """95 % bootstrap interval of the AUROC, resampling objects (a scene's object with all its
    queries: an object's explicit and implicit answers share their map evidence, so they are not
    independent draws)."""
    by: dict[tuple, list[dict]] = {}
    for q in qs:
        by.setdefault((q["scene"], q["object"]), []).append(q)
    groups = list(by.values())
    rng = np.random.default_rng(seed)
    vals = []
    for _ in range(n):
        s = [q for i in rng.integers(0, len(groups), len(groups)) for q in groups[i]]
        y = np.array([q["right"] for q in s], bool)
        if y.any() and not y.all():
            vals.append(auroc(np.array([q["confidence"] for q in s]), y))
    return [round(float(np.percentile(vals, 2.5)), 3), round(float(np.percentile(vals, 97.5)), 3)] if vals else []


def to_rows(report: dict) -> tuple[list[dict], str]:
    rows = []
    for r in report["blocks"]:
        rows.append({"scenes": r["scenes"], "supervision": r["supervision"], "answers": r["answers"],
                     "right": r["right"], "auroc": r["auroc"],
                     "auroc_95ci": "-".join(f"{v:.2f}" for v in r["auroc_95ci"]), "ece": r["ece"],
                     "wrong_success_pct": round(100 * r["wrong_success_share"], 1),
                     "right_returned_pct": round(100 * r["right_returned_share"], 1),
                     "right_explicit_abstained": r["right_explicit_abstained"]})
    ms = report["models"]
    fitted = "; ".join(f"{m['fitted_on']} (threshold {m['threshold']:.2f})" for m in ms.values())
    return rows, (f"one model per supervision, fitted on {fitted}; answers = queries of "
                  f"rg eval --implicit 3 (explicit + 3 implicit per object); right = target right and mean visible "
                  f"IoU >= 0.5; unanswered queries count as abstained; auroc_95ci: bootstrap over objects; confidence adds "
                  f"{1000 * report['seconds_confidence_median']:.1f} ms per query (median)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", action="store_true", help="fit and store the model (default seeds: the fit seeds)")
    ap.add_argument("--seeds", type=int, nargs="*", help="rg synth seeds (default: 201-210; --fit: 101-124)")
    ap.add_argument("--real", nargs="*", default=[str(ROOT.parent / "shared/data/rgbd" / n) for n in REAL],
                    help="real scenes with ground truth, any `rg eval` reads (none: synthetic only)")
    ap.add_argument("--preset", default="offline")
    ap.add_argument("--rows", help="reuse per-query records written by an earlier run (JSON) instead of evaluating")
    ap.add_argument("--out", default="bench_out")
    add_output_flags(ap)
    args = ap.parse_args()
    seeds = args.seeds if args.seeds is not None else (list(FIT_SEEDS) if args.fit else list(HELD_OUT_SEEDS))
    if not args.fit and set(seeds) & set(FIT_SEEDS):
        raise SystemExit(f"seeds {sorted(set(seeds) & set(FIT_SEEDS))} are fit seeds: report on others")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.rows:
        queries = json.loads(Path(args.rows).read_text())
    else:
        with tempfile.TemporaryDirectory() as tmp:
            scenes = make_scenes(seeds, Path(tmp), [] if args.fit else args.real)
            queries = collect(scenes, list(SUPERVISIONS))
        (out / ("confidence_fit_queries.json" if args.fit else "confidence_queries.json")).write_text(json.dumps(queries))
    if args.fit:
        span = (f"{seeds[0]}-{seeds[-1]}" if list(seeds) == list(range(seeds[0], seeds[-1] + 1))
                else " ".join(map(str, seeds)))
        models = {sup: fit(queries, args.preset, sup, f"rg synth seeds {span}, {sup} supervision")
                  for sup in SUPERVISIONS}
        model_path(args.preset).write_text(json.dumps(
            {"preset": args.preset, "by_supervision": {k: m.to_json() for k, m in models.items()}}, indent=1) + "\n")
        for sup, m in models.items():
            print(f"{sup}: {json.dumps(m.metrics)}, threshold {m.threshold:.2f}", file=sys.stderr)
        print(f"wrote {model_path(args.preset)}", file=sys.stderr)
        return 0
    models = {sup: load_model(args.preset, sup) for sup in SUPERVISIONS}
    if models["default"] is None:
        raise SystemExit(f"no confidence model for {args.preset!r}: run with --fit first")
    if args.rows:   # records of an earlier run: score their evidence with the models stored now
        for q in queries:
            if q["answered"]:
                m = models[q["supervision"]]
                q["confidence"] = m.probability(q["evidence"])
                q["success"] = q["confidence"] >= m.threshold
    report = {"models": {k: m.to_json() for k, m in models.items()}, "blocks": [], "seconds_confidence_median": float(np.median(
        [q["seconds_confidence"] for q in queries if q.get("seconds_confidence") is not None] or [0.0]))}
    plots = []
    for sup in SUPERVISIONS:
        model = models[sup]
        mine = [q for q in queries if q["supervision"] == sup]
        groups = {"synthetic": [q for q in mine if q["scene"].startswith("synth")]}
        real = [q for q in mine if not q["scene"].startswith("synth")]
        for name in dict.fromkeys(q["scene"] for q in real):
            groups[f"real: {name}"] = [q for q in real if q["scene"] == name]
        groups["real"], groups["all"] = real, mine
        for name, qs in groups.items():
            if not qs:
                continue
            c = calibration(qs)["all"]
            right_exp = [q for q in qs if q["right"] and q["kind"] == "explicit"]
            report["blocks"].append({"scenes": name, "supervision": sup, **c, "auroc_95ci": auroc_interval(qs),
                                     "right_explicit_abstained": f"{sum(not q['success'] for q in right_exp)}/{len(right_exp)}"})
            print(f"{name} {sup}: {c}", file=sys.stderr)
        png = out / f"confidence_{sup}.png"
        calibration_png(groups["all"], png, model.threshold, f"held-out scenes, {sup} supervision")
        plots.append(png)
    return finish(args, report, "bench_confidence", to_rows, plots=plots)


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
