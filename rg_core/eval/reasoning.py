"""The reasoning benchmark's data (issue 15): the team's description set, split by object into a
tune half and a held-out half with a fixed seed, and random 7-name scene vocabularies.

Every threshold or weight of the text reasoner is fit on the tune half only (fit_text_reasoner);
benchmarks/bench_reasoning.py reports both halves separately.
"""
from __future__ import annotations

import json
import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DESCRIPTIONS = Path(__file__).resolve().parents[1] / "perception" / "data" / "descriptions.json"
SPLIT_SEED = 15
SCENE_SEED = 7


@dataclass(frozen=True)
class Query:
    text: str
    target: str          # "" for an absent thing
    style: str


@dataclass
class Split:
    names: list[str]                 # every object name (the whole catalogue)
    tune: list[Query]
    held: list[Query]
    tune_names: list[str]
    held_names: list[str]


def load_descriptions(path: str | Path = DESCRIPTIONS) -> dict:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"description set not found: {p}")
    return json.loads(p.read_text(encoding="utf-8"))


def split(data: dict, seed: int = SPLIT_SEED) -> Split:
    """Objects (and absent things) halved at random with a fixed seed; a query belongs to the
    half of its object."""
    names = [o["name"] for o in data["objects"]]
    rng = random.Random(seed)
    order = names[:]
    rng.shuffle(order)
    tune_names = sorted(order[: len(order) // 2])
    absent = [Query(d["text"], "", d["style"]) for d in data["absent"]]
    rng.shuffle(absent)
    half = len(absent) // 2
    tune, held = list(absent[:half]), list(absent[half:])
    for o in data["objects"]:
        qs = [Query(d["text"], o["name"], d["style"]) for d in o["descriptions"]]
        (tune if o["name"] in tune_names else held).extend(qs)
    return Split(names, tune, held, tune_names, sorted(set(names) - set(tune_names)))


def scene_vocabularies(queries: list[Query], names: list[str], size: int = 7, seed: int = SCENE_SEED) -> list[list[str]]:
    """One random scene per query: the target (if any) and size-1 (size for absent) other names,
    shuffled; fixed seed."""
    rng = random.Random(seed)
    out = []
    for q in queries:
        others = [n for n in names if n != q.target]
        pick = rng.sample(others, size - 1 if q.target else size)
        v = pick + ([q.target] if q.target else [])
        rng.shuffle(v)
        out.append(v)
    return out


def features(reasoner, queries: list[Query], names: list[str]) -> dict:
    """Everything the text reasoner's scores depend on, for many queries at once:
    name / gloss similarities to every catalogue name [M, N] and to every background concept
    [M, B], and name-to-background similarities [N, B] (the synonym exclusion)."""
    import torch

    from ..perception.reasoning.scoring import NAME_TEMPLATE

    T = reasoner.text
    Q = T([q.text for q in queries])
    ne = T([NAME_TEMPLATE.format(n) for n in names])
    ge = T(reasoner.gloss_texts(names)) if reasoner.knowledge else None
    _, bne, bge = reasoner.background()
    return {"sn": Q @ ne.T, "sg": Q @ ge.T if ge is not None else None, "bn": Q @ bne.T,
            "bg": Q @ bge.T if bge is not None else None, "nb": ne @ bne.T,
            "target": torch.tensor([names.index(q.target) if q.target else -1 for q in queries])}


def components(feat: dict, vocabs: list[list[int]], name_weight: float, background_exclude: float):
    """Per query, within its vocabulary: top-3 catalogue indices, best text score, and the best
    background score among concepts unlike every vocabulary name (-2 when none) [M] each."""
    import torch

    from ..perception.reasoning.scoring import combine

    s = combine(feat["sn"], feat["sg"], name_weight)                          # [M, N]
    b = combine(feat["bn"], feat["bg"], name_weight)                          # [M, B]
    tops, best, bgbest = [], np.zeros(len(vocabs)), np.full(len(vocabs), -2.0)
    cache: dict[tuple, torch.Tensor] = {}
    for i, v in enumerate(vocabs):
        sv = s[i, v]
        order = sv.argsort(descending=True)[:3]
        tops.append([v[int(j)] for j in order])
        best[i] = float(sv[order[0]])
        key = tuple(v)
        if key not in cache:
            cache[key] = feat["nb"][v].max(0).values < background_exclude
        keep = cache[key]
        if keep.any():
            bgbest[i] = float(b[i][keep].max())
    return tops, best, bgbest


def decide(tops, best, bgbest, min_similarity: float, absent_margin: float, prior_reject=None) -> list[int]:
    reject = (best < min_similarity) | ((bgbest - best > absent_margin) if absent_margin >= 0 else False)
    if prior_reject is not None:
        reject = reject | prior_reject
    return [-1 if r else t[0] for r, t in zip(np.atleast_1d(reject), tops)]


def predict(feat: dict, vocabs: list[list[int]], name_weight: float, min_similarity: float, absent_margin: float,
            background_exclude: float) -> tuple[list[int], list[list[int]]]:
    """The text reasoner's implicit decision, vectorised: per query the chosen catalogue index
    (-1: rejected) and its top-3 ranking within its vocabulary."""
    tops, best, bgbest = components(feat, vocabs, name_weight, background_exclude)
    return decide(tops, best, bgbest, min_similarity, absent_margin), tops


def rates(feat: dict, picks: list[int], tops: list[list[int]]) -> dict:
    tgt = feat["target"].tolist()
    real = [i for i, t in enumerate(tgt) if t >= 0]
    absent = [i for i, t in enumerate(tgt) if t < 0]
    n = max(len(real), 1)
    return {"top1": sum(picks[i] == tgt[i] for i in real) / n, "top3": sum(tgt[i] in tops[i] for i in real) / n,
            "false_rejections": sum(picks[i] == -1 for i in real) / n,
            "absent_rejected": sum(picks[i] == -1 for i in absent) / max(len(absent), 1),
            "n_real": len(real), "n_absent": len(absent)}


def fit_text_reasoner(feat: dict, vocabs: list[list[int]], max_false_rejections: float = 0.03,
                      prior_reject: np.ndarray | None = None, catalogue: list[int] | None = None) -> dict:
    """Grid fit on the TUNE half (7-name scenes): name_weight for the sum of 7-name and (given the
    catalogue's indices) whole-catalogue top-1 without rejection (one of them alone picks an
    extreme weight on a few queries' difference), then the
    rejection thresholds for the most absent things rejected with at most max_false_rejections
    of the real descriptions rejected (ties: fewer false rejections, then the larger margin),
    together with the open-set prior's decisions prior_reject [M] (out-of-fold on the tune half),
    which only count where the best text score is below prior_trust (a description that matches
    a vocabulary name well is kept however odd its wording: "a remote to change the channel on
    the television")."""
    best_w, best_acc = 1.0, -1.0
    for w in np.round(np.arange(0.0, 1.01, 0.1), 2):
        acc = 0.0
        for vs in [vocabs] + ([[catalogue] * len(vocabs)] if catalogue else []):
            tops, best, _ = components({**feat, "nb": feat["nb"][:, :1] * 0 + 9}, vs, float(w), 0.0)
            acc += rates(feat, [t[0] for t in tops], tops)["top1"]
        if acc > best_acc + 1e-9:
            best_w, best_acc = float(w), acc
    found = None
    for excl in (0.5, 0.6, 0.7):
        tops, best, bgbest = components(feat, vocabs, best_w, excl)
        for floor in np.round(np.arange(0.0, 0.41, 0.05), 2):
          for trust in (0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.7, 9.0):   # noqa: E111
            pr = None if prior_reject is None else prior_reject & (best < trust)
            for margin in np.round(np.arange(-0.05, 0.31, 0.025), 3):
                r = rates(feat, decide(tops, best, bgbest, float(floor), float(margin), pr), tops)
                if r["false_rejections"] > max_false_rejections:
                    continue
                key = (r["absent_rejected"], -r["false_rejections"], r["top1"], -trust, float(margin))
                if found is None or key > found[0]:
                    found = (key, {"min_similarity": float(floor), "absent_margin": float(margin),
                                   "background_exclude": excl, "prior_trust": trust,
                                   **{f"tune_{k}": v for k, v in r.items()}})
    out = {"name_weight": best_w, "tune_top1_sum_no_rejection": round(best_acc, 4)}
    if found:
        out.update(found[1])
    return out


def fit_domain_prior(text_model, queries: list[Query], C: float = 3.0, max_false_rejections: float = 0.02,
                     folds: int = 5) -> tuple[dict, np.ndarray]:
    """Open-set prior fit on the TUNE half: logistic regression on the MiniLM query embedding,
    real descriptions (1) against absent things (0), class-balanced. The threshold is the
    max_false_rejections quantile of out-of-fold probabilities of the real descriptions (folds by
    object, so a description's own object never taught the model). Returns the stored form and
    the out-of-fold probabilities [M] (for fitting the other thresholds with it)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import GroupKFold

    X = text_model([q.text for q in queries]).numpy().astype(np.float64)
    y = np.array([1 if q.target else 0 for q in queries])
    groups = np.array([f"o:{q.target}" if q.target else f"a:{i}" for i, q in enumerate(queries)])
    oof = np.zeros(len(queries))
    for tr, te in GroupKFold(folds).split(X, y, groups):
        m = LogisticRegression(C=C, class_weight="balanced", max_iter=5000).fit(X[tr], y[tr])
        oof[te] = m.predict_proba(X[te])[:, 1]
    thr = float(np.quantile(oof[y == 1], max_false_rejections))
    m = LogisticRegression(C=C, class_weight="balanced", max_iter=5000).fit(X, y)
    stored = {"version": 1, "about": "Open-set prior of the text reasoner (issue 15): logistic regression on the "
              "all-MiniLM-L6-v2 query embedding, real table-top object descriptions (1) vs absent things (0), "
              "fit by rg_core/eval/reasoning.py fit_domain_prior on the TUNE half of the description set only "
              f"(split seed {SPLIT_SEED}: {int(y.sum())} descriptions, {int((1 - y).sum())} absent things). "
              f"threshold = the {max_false_rejections:.0%} quantile of out-of-fold probabilities of the real "
              "descriptions (5 folds by object).",
              "C": C, "threshold": round(thr, 4), "intercept": float(m.intercept_[0]),
              "coef": [round(float(c), 6) for c in m.coef_[0]],
              "oof_absent_rejected": round(float((oof[y == 0] < thr).mean()), 4),
              "oof_false_rejections": round(float((oof[y == 1] < thr).mean()), 4)}
    return stored, oof
