"""Implicit reasoning on the team's blind description set (issue 15): the old reasoner (MiniLM
nearest name, background-name rejection) against the new one (name + WordNet gloss evidence,
thresholds fit on the tune half), in the same run, both halves reported separately.

    python benchmarks/bench_reasoning.py [--out bench_out/reasoning] [--fit] [--llm [--llm-model GGUF]]
                                         [--subsample K] [--record]

Per half: top-1 / top-3 among random 7-name scene vocabularies (the target always in; fixed seed)
and among the whole catalogue, real descriptions wrongly rejected, absent things rejected
(absent queries get 7 random names), warm latency per implicit query, explicit latency, load time.
--fit refits the text reasoner on the tune half and reports the fitted values (the defaults in
rg_core/perception/reasoning/text.py FIT came from this); nothing is ever fit on the held-out half.
--llm adds the LLM-scored ensemble (rg_core/perception/reasoning/llm_scorer.py, default model the packaged
SmolLM2-135M; --llm-model any GGUF); with --fit its llm_weight and the reduction of a name's token
log-probs (sum or mean) are grid-fit on the TUNE half (sum of 7-name and whole-catalogue top-1 over
the real descriptions), and the LLM ensemble is evaluated on the held-out half only.
--subsample K keeps every K-th query of each half (deterministic; the text fit still uses the
whole tune half) when the LLM makes the full run too slow.
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
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import add_output_flags, finish  # noqa: E402


def to_rows(res: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: per reasoner and half, 7-name and catalogue top-1, rejections, latency."""
    rows = []
    for name in ("old", "new", "new+llm", "new+llm*"):
        for half in ("held_out", "tune"):
            if half not in res.get(name, {}):
                continue
            s, c = res[name][half]["scene7"], res[name][half]["catalogue"]
            rows.append({"reasoner": name, "half": half.replace("_", "-"), "scene7_top1_pct": round(100 * s["top1"], 1),
                         "scene7_top3_pct": round(100 * s["top3"], 1), "catalogue_top1_pct": round(100 * c["top1"], 1),
                         "false_rejections_pct": round(100 * s["false_rejections"], 1),
                         "absent_rejected_pct": round(100 * s["absent_rejected"], 1),
                         "query_median_ms": s["ms_per_query_median"]})
    sp = res["split"]
    return rows, (f"text model {res['text_model']}, {res['threads']} torch threads; {sp['catalogue']} objects split by "
                  f"object ({sp['tune_queries']} tune / {sp['held_queries']} held-out queries); 7-name scenes: target "
                  "always among 7 names")


LLM_WEIGHTS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)


def fit_llm(reasoner, scorer, queries, names: list[str], scenes: list[list[str]]) -> dict:
    """llm_weight and reduce ("sum" / "mean" of a name's token log-probs) for the most 7-name +
    whole-catalogue top-1 (real descriptions of the given half; rejection does not depend on the
    LLM term: it is decided on the text score); ties: the smaller weight, then "sum"."""
    from rg_core.eval.reasoning import features
    from rg_core.perception.reasoning.scoring import combine

    feat = features(reasoner, queries, names)
    text = combine(feat["sn"], feat["sg"], reasoner.name_weight)       # [M, N]
    rows = []   # (query index, catalogue indices, per-name token log-probs)
    call_s = {False: [], True: []}   # seconds per scorer call: 7-name scene, whole catalogue
    t = time.perf_counter()
    for i, (q, scene) in enumerate(tqdm(list(zip(queries, scenes)), desc="llm fit", leave=False)):
        if not q.target:
            continue
        for vocab in (scene, names):
            glosses = dict(zip(vocab, reasoner.gloss_texts(vocab))) if reasoner.knowledge else None
            t1 = time.perf_counter()
            lp = scorer.score_tokens(q.text, vocab, glosses)
            call_s[len(vocab) == len(names)].append(time.perf_counter() - t1)
            rows.append((i, [names.index(n) for n in vocab], lp, len(vocab) == len(names)))
    secs = time.perf_counter() - t
    table, best = [], None
    for reduce in ("sum", "mean"):
        f = np.sum if reduce == "sum" else np.mean
        lls = [torch.tensor([float(f(x)) for x in lp], dtype=torch.float64) for _, _, lp, _ in rows]
        for w in LLM_WEIGHTS:
            hit = {False: [], True: []}
            for (i, idx, _, cat), ll in zip(rows, lls):
                s = combine(text[i, idx].double(), None, 1.0, ll, w)
                hit[cat].append(idx[int(s.argmax())] == names.index(queries[i].target))
            r = {"reduce": reduce, "llm_weight": w, "top1_7": round(float(np.mean(hit[False])), 4),
                 "top1_catalogue": round(float(np.mean(hit[True])), 4)}
            table.append(r)
            key = (r["top1_7"] + r["top1_catalogue"], -w, reduce == "sum")
            if best is None or key > best[0]:
                best = (key, r)
    return {"llm_weight": best[1]["llm_weight"], "llm_reduce": best[1]["reduce"],
            "tune_top1_7": best[1]["top1_7"], "tune_top1_catalogue": best[1]["top1_catalogue"],
            "n_real": len(rows) // 2, "seconds": round(secs, 1),
            "llm_ms_per_call_7_median": round(1000 * float(np.median(call_s[False])), 1),
            "llm_ms_per_call_catalogue_median": round(1000 * float(np.median(call_s[True])), 1),
            "best_nonzero": max((r for r in table if r["llm_weight"] > 0),
                                key=lambda r: (r["top1_7"] + r["top1_catalogue"], -r["llm_weight"])),
            "grid": table}


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
    ap.add_argument("--llm-model", default="", help="GGUF for --llm (default: the packaged SmolLM2-135M)")
    ap.add_argument("--llm-knowledge-max", type=int, default=0,
                    help="list the names (with glosses) in the LLM prompt for scenes of at most this many names")
    ap.add_argument("--subsample", type=int, default=1, help="keep every K-th query of each half")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--text-model", default="minilm",
                    help="both reasoners' text encoder (reason.text_model): minilm (packaged), mpnet "
                         "(all-mpnet-base-v2 from its PyPI parts) or a sentence-transformers folder; with --fit "
                         "a named encoder's fit goes to rg_core/perception/data/reasoner_fit_NAME.json and "
                         "domain_prior_NAME.json (a folder's to OUT/), never over MiniLM's")
    ap.add_argument("--llm-threads", type=int, default=0, help="llama.cpp threads (0: --threads)")
    add_output_flags(ap, json_flag=False)
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(a.threads)
    from rg_core.eval.reasoning import features, fit_domain_prior, fit_text_reasoner, load_descriptions, scene_vocabularies, split
    from rg_core.perception.embed import MiniLMText
    from rg_core.perception.reasoning import TextReasoner
    from rg_core.perception.text_cache import CachedText

    sp = split(load_descriptions())
    tune_all = sp.tune
    if a.subsample > 1:
        sp.tune, sp.held = sp.tune[::a.subsample], sp.held[::a.subsample]
    t = time.perf_counter()
    from rg_core.perception.sentence_text import DATA, FIT_KEYS, encoder_fit, fit_paths, is_named, make_text_model

    model = make_text_model(a.text_model) or MiniLMText()
    load_model = time.perf_counter() - t
    other = a.text_model not in ("", "minilm")
    fit_file, prior_file = (fit_paths(a.text_model, DATA) if is_named(a.text_model) else fit_paths("folder", out))
    if other:   # the package's prior belongs to MiniLM: this encoder's own, or none before a fit
        import rg_core.perception.reasoning.open_set as reasoner_module

        reasoner_module.DOMAIN_PRIOR_PATH = prior_file
    # Separate caches: neither reasoner sees the other's query embeddings (honest warm latency).
    t = time.perf_counter()
    old = TextReasoner(use_knowledge=False, name_weight=1.0, min_similarity=0.30, absent_margin=0.15,
                       background_exclude=0.6, domain_prior=False, text_model=CachedText(model))
    old.background()
    load_old = time.perf_counter() - t
    t = time.perf_counter()
    new = TextReasoner(text_model=CachedText(model), **(encoder_fit(a.text_model)[0] if other else {}))
    new.background()
    load_new = time.perf_counter() - t
    res = {"date": time.strftime("%Y-%m-%d"), "threads": a.threads, "text_model": a.text_model,
           "subsample": a.subsample, "split": {"tune_objects": len(sp.tune_names), "held_objects": len(sp.held_names),
                     "tune_queries": len(sp.tune), "held_queries": len(sp.held), "catalogue": len(sp.names)},
           "load_s": {"minilm": round(load_model, 2), "old": round(load_old, 2), "new": round(load_new, 2)}}
    if a.fit:
        from rg_core.perception.reasoning.open_set import DOMAIN_PRIOR_PATH

        prior, oof = fit_domain_prior(new.text, tune_all)
        DOMAIN_PRIOR_PATH.write_text(json.dumps(prior) + "\n", encoding="utf-8")
        vocabs = [[sp.names.index(n) for n in v] for v in scene_vocabularies(tune_all, sp.names)]
        res["fit_on_tune"] = {"domain_prior": {k: v for k, v in prior.items() if k != "coef"},
                              **fit_text_reasoner(features(new, tune_all, sp.names), vocabs,
                                                  prior_reject=oof < prior["threshold"],
                                                  catalogue=list(range(len(sp.names))))}
        f = res["fit_on_tune"]
        if other:
            fit_file.write_text(json.dumps({**{k: f[k] for k in FIT_KEYS}, "text_model": a.text_model,
                                            "fit": "benchmarks/bench_reasoning.py --fit --text-model "
                                                   f"{a.text_model}, tune half only, {res['date']}"}, indent=1) + "\n")
        new = TextReasoner(text_model=CachedText(model), name_weight=f["name_weight"], min_similarity=f["min_similarity"],
                           absent_margin=f["absent_margin"], background_exclude=f["background_exclude"],
                           prior_trust=f["prior_trust"])
    reasoners = {"old": old, "new": new}
    if a.llm:
        try:
            from rg_core.perception.reasoning.llm_scorer import LLMChoiceScorer
            t = time.perf_counter()
            scorer = LLMChoiceScorer(model_path=a.llm_model or None, n_threads=a.llm_threads or a.threads, memo_size=8192,
                                     knowledge_max_names=a.llm_knowledge_max)
            res["llm"] = {"model": scorer.model_name, "file": scorer.path.name, "load_s": round(time.perf_counter() - t, 2),
                          "chat_template": bool(scorer.template), "knowledge_max_names": a.llm_knowledge_max,
                          "threads": a.llm_threads or a.threads}
            w = 0.1
            if a.fit:
                res["fit_on_tune"]["llm"] = fit = fit_llm(new, scorer, sp.tune, sp.names,
                                                          scene_vocabularies(sp.tune, sp.names))
                w, scorer.reduce = fit["llm_weight"], fit["llm_reduce"]
                print("llm fit:", json.dumps({k: v for k, v in fit.items() if k != "grid"}))
            res["llm"]["llm_weight"], res["llm"]["reduce"] = w, scorer.reduce
            reasoners["new+llm"] = TextReasoner(text_model=CachedText(model), llm_scorer=scorer, llm_weight=w,
                                                name_weight=new.name_weight, min_similarity=new.min_similarity,
                                                absent_margin=new.absent_margin,
                                                background_exclude=new.background_exclude, prior_trust=new.prior_trust)
            reasoners["new+llm"].background()
            if a.fit and w == 0:   # the fit turned the LLM off: also show the best non-zero tune weight held out
                bn = res["fit_on_tune"]["llm"]["best_nonzero"]
                scorer2 = LLMChoiceScorer(model_path=a.llm_model or None, n_threads=a.llm_threads or a.threads,
                                          memo_size=8192, knowledge_max_names=a.llm_knowledge_max, reduce=bn["reduce"])
                reasoners["new+llm*"] = TextReasoner(
                    text_model=CachedText(model), llm_scorer=scorer2, llm_weight=bn["llm_weight"],
                    name_weight=new.name_weight, min_similarity=new.min_similarity, absent_margin=new.absent_margin,
                    background_exclude=new.background_exclude, prior_trust=new.prior_trust)
                reasoners["new+llm*"].background()
                res["llm"]["best_nonzero"] = bn
        except Exception as exc:  # noqa: BLE001
            res["llm"] = f"not run: {type(exc).__name__}: {exc}"
    for half, qs in (("tune", sp.tune), ("held_out", sp.held)):
        scenes = scene_vocabularies(qs, sp.names)
        cat = [sp.names] * len(qs)
        for name, r in reasoners.items():
            if name.startswith("new+llm") and half == "tune":
                continue   # the LLM's tune-half figures are in fit_on_tune (its time goes to the held-out half)
            if r.llm_scorer is not None and r.llm_weight:
                r.llm_scorer._memo.clear()   # every held-out query is scored afresh: honest latency
            res.setdefault(name, {})[half] = {"scene7": evaluate(r, qs, sp.names, scenes, f"{name} {half} 7"),
                                             "catalogue": evaluate(r, qs, sp.names, cat, f"{name} {half} all")}
    for name, r in reasoners.items():
        res[name]["explicit_ms_median"] = explicit_latency(r, sp.names)
    write_outputs(res, out)
    print(json.dumps(res, indent=1))
    return finish(a, res, "bench_reasoning", to_rows, plots=[out / "reasoning.png"])


def write_outputs(res: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [k for k in ("old", "new", "new+llm", "new+llm*") if k in res]
    rows = ["| reasoner | half | 7-name top-1 | top-3 | catalogue top-1 | top-3 | false rej. (7) | absent rej. (7) "
            "| absent rej. (cat.) | ms/query (7) | ms/query (cat.) |", "|" + "---|" * 11]
    for n in names:
        for h in ("tune", "held_out"):
            if h not in res[n]:
                continue
            s, c = res[n][h]["scene7"], res[n][h]["catalogue"]
            rows.append(f"| {n} | {h} | {s['top1']:.1%} | {s['top3']:.1%} | {c['top1']:.1%} | {c['top3']:.1%} | "
                        f"{s['false_rejections']:.1%} | {s['absent_rejected']:.1%} | {c['absent_rejected']:.1%} | "
                        f"{s['ms_per_query_median']} | {c['ms_per_query_median']} |")
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
