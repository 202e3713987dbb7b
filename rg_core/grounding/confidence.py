"""How likely an answer is right: the evidence a query already computed -> a probability.

A logistic model over a few evidence features (`evidence`) gives P(right), where right means the
reasoner's target is the true object and the grounded group's visible masks overlap it with
IoU >= 0.5. It is fitted on scenes that are never the ones it is reported on
(benchmarks/bench_confidence.py --fit) and stored per backend preset in
rg_core/perception/data/confidence_<preset>.json, one model per supervision source of the map (the
preset's models or ground truth: their evidence lives on different scales), each with the abstention
threshold chosen from its risk-coverage curve. A preset without a fitted model keeps the uncalibrated
score and never abstains (docs/confidence.md).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from .carve import SIZE_TOL, dilated, sight
from .relevancy import CANONICAL, relevancy_pca

DATA = Path(__file__).resolve().parents[1] / "perception" / "data"
BACKGROUND_SAMPLE = 2048   # Gaussians whose relevancy stands for the map's background
AGREE_POINTS = 400         # group Gaussians projected into the other keyframes
CLIP = 3.0                 # standardised features are clipped to this many spreads

# name -> what it measures (the explanation's words). A model reads the subset it was fitted on
# (ConfidenceModel.features). Counts that grow with the map (how many keyframes see the group) are
# evidence in the result but never model inputs: they would not transfer to a map of another size.
EVIDENCE = {
    "mask_similarity": "best mask's similarity to the target name",
    "name_margin": "reference mask's margin to the runner-up name",
    "margin_gap": "reference mask's name margin short of the map's most target-specific mask",
    "name_distinctness": "how far the target name lies from the nearest other name the scene holds",
    "mask_share": "reference mask's share of its image",
    "relevancy_peak": "relevancy peak",
    "relevancy_z": "relevancy peak against the map's background",
    "group_relevancy_z": "group's relevancy against the map's background",
    "relevancy_contrast": "group's relevancy above the most relevant 1 % of the rest of the map",
    "view_agreement": "share of the group other views see inside their mask of the target",
    "group_name_margin": "name margin of the masks other views hold the group in",
    "group_similarity": "instance-feature similarity of the group to the peak",
    "reasoner": "reasoner confidence",
}
FEATURES = tuple(EVIDENCE)   # what a model may read; views_seen and the background are reported only


@dataclass
class ConfidenceModel:
    """P(right) = sigmoid(intercept + coef . (x - mean) / std), x the evidence named by `features`."""

    preset: str
    supervision: str                 # the maps' supervision source it was fitted on: default | oracle
    features: list[str]              # [F] its inputs, a subset of FEATURES
    mean: np.ndarray                 # [F]
    std: np.ndarray                  # [F]
    coef: np.ndarray                 # [F]
    intercept: float
    threshold: float                 # default abstention threshold (risk-coverage on the fit scenes)
    fitted_on: str = ""
    metrics: dict = field(default_factory=dict)

    def inputs(self, ev: dict[str, float]) -> np.ndarray:  # -> [F]
        return np.array([ev.get(k, math.nan) for k in self.features], np.float64)

    def standardise(self, x: np.ndarray) -> np.ndarray:  # [..., F] -> [..., F]
        """Standardised features, a missing one as the fit's mean, each clipped to +-CLIP spreads:
        a map unlike the fit scenes must not extrapolate the linear model into certainty."""
        x = np.where(np.isfinite(x), x, self.mean)
        return np.clip((x - self.mean) / self.std, -CLIP, CLIP)

    def probabilities(self, x: np.ndarray) -> np.ndarray:  # inputs [..., F] -> [...]
        return 1.0 / (1.0 + np.exp(-np.clip(self.intercept + self.standardise(x) @ self.coef, -50, 50)))

    def probability(self, ev: dict[str, float]) -> float:
        return float(self.probabilities(self.inputs(ev)))

    def weakest(self, ev: dict[str, float], n: int = 2) -> list[str]:
        """The features that pull the probability down most: those the model reads "more is better"
        (positive weight) that lie below the fit's mean, the largest pull first."""
        contrib = np.where(self.coef > 0, self.coef * self.standardise(self.inputs(ev)), 0.0)
        return [self.features[i] for i in np.argsort(contrib)[:n] if contrib[i] < 0]

    def to_json(self) -> dict:
        return {"preset": self.preset, "supervision": self.supervision, "features": list(self.features),
                "mean": self.mean.tolist(), "std": self.std.tolist(), "coef": self.coef.tolist(),
                "intercept": self.intercept, "threshold": self.threshold, "fitted_on": self.fitted_on,
                "metrics": self.metrics}

    @staticmethod
    def from_json(d: dict) -> "ConfidenceModel":
        feats = list(d.get("features", []))
        if not feats or set(feats) - set(FEATURES):
            raise ValueError(f"confidence model for {d.get('preset')!r} reads features {feats}, this code measures "
                             f"{list(FEATURES)}: refit with python benchmarks/bench_confidence.py --fit")
        return ConfidenceModel(d["preset"], d.get("supervision", "default"), feats, np.asarray(d["mean"], np.float64),
                               np.asarray(d["std"], np.float64),
                               np.asarray(d["coef"], np.float64), float(d["intercept"]), float(d["threshold"]),
                               d.get("fitted_on", ""), d.get("metrics", {}))


def model_path(preset: str) -> Path:
    return DATA / f"confidence_{preset}.json"


@lru_cache(maxsize=8)
def load_model(preset: str, supervision: str = "default") -> ConfidenceModel | None:
    """The model fitted for `preset` on maps of `supervision` (default | oracle; the default one when
    that source has none), or None when none was fitted."""
    p = model_path(preset)
    if not p.is_file():
        return None
    models = json.loads(p.read_text(encoding="utf-8"))["by_supervision"]
    return ConfidenceModel.from_json(models.get(supervision, models["default"]))


def supervision_of(g) -> str:
    """The supervision source of the grounder's map (maps saved before it was recorded: default)."""
    return getattr(g.mapper.supervision, "source", "default")


def _robust(x: torch.Tensor) -> tuple[float, float]:
    """median and 1.4826 * MAD (a standard deviation for normal data), MAD floored at 1e-3."""
    med = float(x.median())
    return med, 1.4826 * max(float((x - med).abs().median()), 1e-3)


def background(g, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(ids [M] of up to BACKGROUND_SAMPLE Gaussians, a fixed random sample, and the PCA codes [M, k]
    of their language feature at `scale`), cached with the map: the distribution a peak must stand
    out of."""
    g._check_cache()
    N = len(g.field.latents)

    def make():
        idx = torch.from_numpy(np.sort(np.random.default_rng(g.gcfg.seed).choice(N, min(N, BACKGROUND_SAMPLE),
                                                                                replace=False)))
        with torch.no_grad():
            return idx, g.field.language(g.field.latents[idx], scale)
    return g.cache.get("background", (round(scale, 4), N), make)


def view_agreement(g, ref, ids: np.ndarray, target: torch.Tensor, other: torch.Tensor | None) -> tuple[float, int, float]:
    """Over the keyframes other than the reference that see the group (>= 20 % of its sampled
    Gaussians, carve.sight's visibility test): the mean share of the seen ones inside that keyframe's
    best mask of the target, how many such keyframes, and the mean name margin (similarity to
    `target` [D] less the best of `other` [O, D]) of the mask in each that holds most of the seen
    ones (the smaller of equals). (nan, 0, nan) when none sees it."""
    if not len(ids):
        return math.nan, 0, math.nan
    gs = g.mapper.gaussians
    pick = ids if len(ids) <= AGREE_POINTS else ids[np.linspace(0, len(ids) - 1, AGREE_POINTS).astype(np.int64)]
    pts = gs.means.detach()[torch.from_numpy(pick)].numpy().astype(np.float64)        # [P, 3] world
    tol = SIZE_TOL * gs.scales.detach()[torch.from_numpy(pick)].max(1).values.numpy()  # [P] as carve.mask_votes
    sup = g.mapper.supervision.by_keyframe
    border = g.vote_border()
    cands = [c for c in ref.candidates if c.keyframe.index != ref.keyframe.index
             and sup[c.keyframe.index].masks[c.index].shape == tuple(c.keyframe.depth.shape)]
    if not cands:
        return math.nan, 0, math.nan
    kfs = [c.keyframe for c in cands]
    ons, seens, rs, us = sight(pts, np.stack([kf.K for kf in kfs]), np.stack([kf.cam_to_world for kf in kfs]),
                               [kf.depth.numpy() for kf in kfs], tol)                  # [V, P] each
    shares, margins = [], []
    for c, seen, r, u in zip(cands, seens, rs, us):
        if seen.sum() < 0.2 * len(pts):
            continue
        s = sup[c.keyframe.index]
        m = dilated(s.masks[c.index], border)
        shares.append(float((m[r[seen], u[seen]] > 0).mean()))
        held = s.masks[:, r[seen], u[seen]].sum(1)                                    # [M] seen points per mask
        best = np.flatnonzero(held == held.max())
        j = int(best[np.argmin(s.masks[best].sum((1, 2)))]) if len(best) > 1 else int(best[0])
        e = torch.nn.functional.normalize(s.embeddings[j].float(), dim=-1)
        margins.append(float(e @ target) - (float((other @ e).max()) if other is not None else -1.0))
    if not shares:
        return math.nan, 0, math.nan
    return float(np.mean(shares)), len(shares), float(np.mean(margins))


def evidence(g, reasoning, ref, pk, vocabulary: list[str], ids: np.ndarray, group_similarity: float) -> dict[str, float]:
    """The evidence behind an answer (EVIDENCE, views_seen and the background's median and spread):
    a few ms on top of the query."""
    sset = g.mapper.supervision
    sup = sset.by_keyframe[ref.keyframe.index]
    others = [n for n in dict.fromkeys(vocabulary) if n != reasoning.target]
    other = g.encode(others) if others else None                                                  # [O, D]
    every = torch.nn.functional.normalize(torch.cat([s.embeddings for s in sset.by_keyframe.values()
                                                     if len(s.embeddings)]).float(), dim=-1)       # [M, D]
    margins = every @ ref.target - ((every @ other.T).max(-1).values if others else -1.0)       # [M]
    emb = torch.nn.functional.normalize(sup.embeddings[ref.mask_index].float(), dim=-1)           # [D]
    runner_up = float((other @ emb).max()) if others else -1.0
    name_margin = float(emb @ ref.target) - runner_up
    target_text = g.encode([reasoning.target])[0]
    # against the names the caller says the scene holds (the confusers that matter); with none
    # declared, against the whole vocabulary (more names: lower, the cautious side)
    declared = [n for n in dict.fromkeys(list(g.scene_names) + list(g.gcfg.vocabulary)) if n != reasoning.target]
    near = g.encode(declared) if declared else other
    distinct = 1.0 - float((near @ target_text).max()) if near is not None else 1.0
    pca = g.mapper.supervision.pca.pca
    texts = (target_text, g.encode(list(CANONICAL)))
    bg_ids, bg_codes = background(g, ref.scale)
    bg = relevancy_pca(bg_codes, pca.components, pca.mean, *texts)                                # [M]
    med, spread = _robust(bg)
    ids = np.asarray(ids, np.int64)
    with torch.no_grad():
        z = g.field.language(g.field.latents[torch.from_numpy(ids)], ref.scale)
    group_rel = float(relevancy_pca(z, pca.components, pca.mean, *texts).mean()) if len(ids) else med
    rest = bg[~torch.from_numpy(np.isin(bg_ids.numpy(), ids))]
    top = float(torch.quantile(rest, 0.99)) if len(rest) else med
    agree, seen, group_margin = view_agreement(g, ref, ids, ref.target, other)
    return {"mask_similarity": float(ref.similarity), "name_margin": name_margin,
            "margin_gap": name_margin - float(margins.max()), "name_distinctness": distinct,
            "mask_share": float(ref.mask.float().mean()),
            "relevancy_peak": float(pk.relevancy), "relevancy_z": (float(pk.relevancy) - med) / spread,
            "group_relevancy_z": (group_rel - med) / spread, "relevancy_contrast": (group_rel - top) / spread,
            "view_agreement": agree, "views_seen": float(seen), "group_name_margin": group_margin,
            "group_similarity": float(group_similarity), "reasoner": float(reasoning.confidence),
            "background_median": med, "background_spread": spread}


def describe(ev: dict[str, float], names: list[str]) -> str:
    """Words and figures for the named evidence ("relevancy peak 0.483 against the map's 0.470 +- 0.010")."""
    out = []
    for n in names:
        v = ev.get(n, math.nan)
        if n in ("relevancy_z", "relevancy_peak"):
            out.append(f"relevancy peak {ev['relevancy_peak']:.3f} against the map's {ev['background_median']:.3f} "
                       f"+- {ev['background_spread']:.3f}")
        elif n == "group_relevancy_z":
            out.append(f"the group's relevancy stands {v:.1f} spreads above the map's")
        elif n in ("view_agreement", "views_seen"):
            out.append("no other view sees the group" if not math.isfinite(ev["view_agreement"]) else
                       f"{int(ev['views_seen'])} other views see the group, {100 * ev['view_agreement']:.0f} % of it "
                       f"inside their mask of the target")
        else:
            out.append(f"{EVIDENCE[n]} {v:.2f}")
    return "; ".join(dict.fromkeys(out))


def threshold(model: ConfidenceModel | None, min_confidence: float) -> float | None:
    """The abstention threshold: ground.min_confidence when >= 0, else the model's fitted one;
    None without a model (an uncalibrated score never abstains)."""
    if model is None:
        return None
    return model.threshold if min_confidence < 0 else min_confidence


def assess(g, res, reasoning, ref, pk, group_similarity: float) -> tuple[bool, str]:
    """Fill res.evidence and res.confidence (P(right) from the preset's model; without one, the
    uncalibrated product of reasoner, relevancy and group scores already in the objects) and
    scale the objects' confidences alike. -> (answer, or abstain and why)."""
    first = res.objects[0]
    res.evidence = evidence(g, reasoning, ref, pk, g.vocabulary(), first.gaussian_ids, group_similarity)
    model = load_model(g.cfg.models.preset, supervision_of(g))
    raw = first.confidence
    thr = threshold(model, g.gcfg.min_confidence)
    if model is None:
        res.confidence = raw
        return True, ""
    p = model.probability(res.evidence)
    for o in res.objects:
        o.confidence = p * (o.confidence / raw if raw > 0 else 1.0)
    res.confidence = p
    if p >= thr:
        return True, ""
    return False, f"confidence {p:.2f} < {thr:.2f} ({describe(res.evidence, model.weakest(res.evidence))})"
