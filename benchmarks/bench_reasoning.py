"""Implicit reasoning on the team's blind description set (issue 15): the old reasoner (MiniLM
nearest name, background-name rejection) against the new one (name + WordNet gloss evidence,
thresholds fit on the tune half), in the same run, both halves reported separately.

    python benchmarks/bench_reasoning.py [--out bench_out/reasoning] [--fit] [--llm]

Per half: top-1 / top-3 among random 7-name scene vocabularies (the target always in; fixed seed)
and among the whole catalogue, real descriptions wrongly rejected, absent things rejected
(absent queries get 7 random names), warm latency per implicit query, explicit latency, load time.
--fit refits the text reasoner on the tune half and reports the fitted values (the defaults in
rg_core/perception/reasoner.py FIT came from this); nothing is ever fit on the held-out half.
--llm adds the LLM-scored ensemble when rg_core.perception.llm_scorer is importable.
Writes reasoning.json, reasoning.md (table) and reasoning.png.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rg_core.util import run_json_script  # noqa: E402


def evaluate(reasoner, queries, names, vocabs, label: str) -> dict:
    """Real reason() calls: decisions, top-3 from the reasoner's own scores, warm latency."""
    picks, top3, secs = [], [], []
    for q, v in tqdm(list(zip(queries, vocabs)), desc=label, leave=False):
        t = time.perf_counter()
        r = reasoner.reason(q.text, v, mode="implicit")
        secs.append(time.perf_counter() - t)
        picks.append(r.target)
        if q.target:
            s = reasoner.scores(q.text, v)["score"]
            top3.append(q.target in [v[int(i)] for i in s.argsort(descending=True)[:3]])
    real = [i for i, q in enumerate(queries) if q.target]
    absent = [i for i, q in enumerate(queries) if not q.target]
    n = max(len(real), 1)
    return {"top1": round(sum(picks[i] == queries[i].target for i in real) / n, 4),
            "top3": round(sum(top3) / n, 4) if top3 else None,
            "false_rejections": round(sum(picks[i] == "" for i in real) / n, 4),
            "absent_rejected": round(sum(picks[i] == "" for i in absent) / max(len(absent), 1), 4),
            "n_real": len(real), "n_absent": len(absent),
            "ms_per_query_median": round(1000 * float(np.median(secs)), 1),
            "ms_per_query_p90": round(1000 * float(np.percentile(secs, 90)), 1)}


def explicit_latency(reasoner, names) -> float:
    secs = []
    for n in names:
        t = time.perf_counter()
        r = reasoner.reason(f"the {n}", names)
        secs.append(time.perf_counter() - t)
        assert r.target == n or not r.implicit
    return round(1000 * float(np.median(secs)), 2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "bench_out" / "reasoning"))
    ap.add_argument("--fit", action="store_true", help="refit the new reasoner on the tune half")
    ap.add_argument("--llm", action="store_true", help="also the LLM-scored ensemble (needs llm_scorer)")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(a.threads)
    from rg_core.eval.reasoning import features, fit_domain_prior, fit_text_reasoner, load_descriptions, scene_vocabularies, split
    from rg_core.perception.embed import MiniLMText
    from rg_core.perception.reasoner import TextReasoner, _CachedText

    sp = split(load_descriptions())
    t = time.perf_counter()
    model = MiniLMText()
    load_model = time.perf_counter() - t
    # Separate caches: neither reasoner sees the other's query embeddings (honest warm latency).
    t = time.perf_counter()
    old = TextReasoner(use_knowledge=False, name_weight=1.0, min_similarity=0.30, absent_margin=0.15,
                       background_exclude=0.6, domain_prior=False, text_model=_CachedText(model))
    old.background()
    load_old = time.perf_counter() - t
    t = time.perf_counter()
    new = TextReasoner(text_model=_CachedText(model))
    new.background()
    load_new = time.perf_counter() - t
    res = {"date": time.strftime("%Y-%m-%d"), "threads": a.threads,
           "split": {"tune_objects": len(sp.tune_names), "held_objects": len(sp.held_names),
                     "tune_queries": len(sp.tune), "held_queries": len(sp.held), "catalogue": len(sp.names)},
           "load_s": {"minilm": round(load_model, 2), "old": round(load_old, 2), "new": round(load_new, 2)}}
    if a.fit:
        from rg_core.perception.reasoner import DOMAIN_PRIOR_PATH

        prior, oof = fit_domain_prior(new.text, sp.tune)
        DOMAIN_PRIOR_PATH.write_text(json.dumps(prior) + "\n", encoding="utf-8")
        vocabs = [[sp.names.index(n) for n in v] for v in scene_vocabularies(sp.tune, sp.names)]
        res["fit_on_tune"] = {"domain_prior": {k: v for k, v in prior.items() if k != "coef"},
                              **fit_text_reasoner(features(new, sp.tune, sp.names), vocabs,
                                                  prior_reject=oof < prior["threshold"],
                                                  catalogue=list(range(len(sp.names))))}
        f = res["fit_on_tune"]
        new = TextReasoner(text_model=_CachedText(model), name_weight=f["name_weight"], min_similarity=f["min_similarity"],
                           absent_margin=f["absent_margin"], background_exclude=f["background_exclude"],
                           prior_trust=f["prior_trust"])
    reasoners = {"old": old, "new": new}
    if a.llm:
        try:
            from rg_core.perception.llm_scorer import LLMChoiceScorer
            reasoners["new+llm"] = TextReasoner(text_model=_CachedText(model), llm_scorer=LLMChoiceScorer(),
                                                llm_weight=res.get("fit_on_tune", {}).get("llm_weight", 0.1))
        except Exception as exc:  # noqa: BLE001
            res["llm"] = f"not run: {type(exc).__name__}: {exc}"
    for half, qs in (("tune", sp.tune), ("held_out", sp.held)):
        scenes = scene_vocabularies(qs, sp.names)
        cat = [sp.names] * len(qs)
        for name, r in reasoners.items():
            res.setdefault(name, {})[half] = {"scene7": evaluate(r, qs, sp.names, scenes, f"{name} {half} 7"),
                                             "catalogue": evaluate(r, qs, sp.names, cat, f"{name} {half} all")}
    for name, r in reasoners.items():
        res[name]["explicit_ms_median"] = explicit_latency(r, sp.names)
    write_outputs(res, out)
    print(json.dumps(res, indent=1))
    return 0


def write_outputs(res: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [k for k in ("old", "new", "new+llm") if k in res]
    rows = ["| reasoner | half | 7-name top-1 | top-3 | catalogue top-1 | top-3 | false rej. (7) | absent rej. (7) "
            "| absent rej. (cat.) | ms/query (7) |", "|" + "---|" * 10]
    for n in names:
        for h in ("tune", "held_out"):
            s, c = res[n][h]["scene7"], res[n][h]["catalogue"]
            rows.append(f"| {n} | {h} | {s['top1']:.1%} | {s['top3']:.1%} | {c['top1']:.1%} | {c['top3']:.1%} | "
                        f"{s['false_rejections']:.1%} | {s['absent_rejected']:.1%} | {c['absent_rejected']:.1%} | "
                        f"{s['ms_per_query_median']} |")
    (out / "reasoning.md").write_text("\n".join(rows) + "\n")
    (out / "reasoning.json").write_text(json.dumps(res, indent=1))
    print("\n".join(rows))
    metrics = [("7-name top-1", "scene7", "top1"), ("catalogue top-1", "catalogue", "top1"),
               ("false rej.", "scene7", "false_rejections"), ("absent rej.", "scene7", "absent_rejected")]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    w = 0.8 / max(len(names), 1)
    for k, n in enumerate(names):
        vals = [res[n]["held_out"][sec][m] for _, sec, m in metrics]
        ax.bar(np.arange(len(metrics)) + k * w, vals, w, label=n)
    ax.set_xticks(np.arange(len(metrics)) + w * (len(names) - 1) / 2, [m[0] for m in metrics])
    ax.set_ylim(0, 1)
    ax.set_title("held-out half (objects never used for tuning)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "reasoning.png", dpi=100)


if __name__ == "__main__":
    run_json_script(main)
