"""When to stop training the field: its accuracy on held-out pixels stops improving.

Each supervised view keeps a fixed share of its pixels (`FieldConfig.holdout`) out of training.
Every `check_every` steps the field is measured, without gradients, on a fixed sample of those
pixels in up to `holdout_views` supervised views: language accuracy (the prediction at a mask's
scale is nearest to that mask's embedding) and instance accuracy (pixel pairs closer than margin / 2
exactly when they share a group), and the training loss. Training has converged once the best mean
accuracy gained less than `converge_tol` over the last `converge_window` steps: the accuracies
flatten where grounding stops changing, while the loss keeps falling slowly for hundreds of steps
(docs/field.md). Steps are counted, not seconds, so the same seed stops at the same step on any CPU.
New supervision (views, PCA basis) changes the evaluation set and restarts the test.
`train_until` is the training loop (FeatureField.train): budgets, the stop test, interruptions.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from .losses import shares_group


def holdout_pixels(n_pixels: int, share: float, seed: int, view: int) -> torch.Tensor:
    """[n_pixels] bool: the pixels of one view never trained on (fixed per seed and view)."""
    if share <= 0:
        return torch.zeros(n_pixels, dtype=torch.bool)
    g = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(view))
    return torch.rand(n_pixels, generator=g) < share


@dataclass
class Probe:
    """The fixed evaluation sample of one held-out view."""

    kf: object
    pix: torch.Tensor      # [P] pixel indices (held-out pixels, drawn with the training weights)
    own: torch.Tensor      # [S] mask scales L_lang is measured at
    sampled: list          # scales L_in (and L_lang) are measured at: one between each pair of mask scales


@dataclass
class Convergence:
    """The stop test's state on one evaluation set; `decision` is set once it converged."""

    key: tuple = ()
    start: int = 0                                   # field.steps when this evaluation set began
    history: list = field(default_factory=list)      # (steps since start, field seconds, accuracy, loss,
                                                     #  language accuracy, instance accuracy) per check
    probes: list = field(default_factory=list)
    decision: dict | None = None

    def converged(self, tol: float, window: int) -> bool:
        """The best accuracy gained less than tol over the last `window` steps."""
        ok = [h for h in self.history if np.isfinite(h[2])]  # a diverged measurement is never the best
        if not self.history or self.history[-1][0] < window or not ok:
            return False
        n = self.history[-1][0]
        before = [h[2] for h in ok if h[0] <= n - window]
        return bool(before) and max(h[2] for h in ok) - max(before) < tol


def _probe(field, kf) -> Probe | None:
    _, _, _, masks, scales, weights, held = field._train_view(kf)
    w = torch.where(held, weights, torch.zeros(()))
    if not bool((w > 0).any()):
        return None
    g = torch.Generator().manual_seed(field.cfg.seed + 7919 * kf.index)
    P = min(field.cfg.rays_per_step, int((w > 0).sum()))
    pix = torch.multinomial(w, P, replacement=False, generator=g)
    u = torch.unique(scales[torch.isfinite(scales)])
    own = u if len(u) <= 16 else u[torch.linspace(0, len(u) - 1, 16).round().long()]
    mids = [(float(u[j]) + float(u[j + 1])) / 2 for j in range(len(u) - 1)]
    if len(u) and not mids:
        mids = [float(u[-1]) * 1.25]
    k = field.cfg.scales_per_step
    sampled = [mids[int(i)] for i in np.linspace(0, len(mids) - 1, min(k, len(mids))).round()] if mids else []
    return Probe(kf, pix, own, sampled)


def _key(field, kfs) -> tuple:
    sset = field.mapper.supervision
    return (tuple(kf.index for kf in kfs), tuple(sset.by_keyframe[kf.index].serial for kf in kfs), sset.pca.version)


@torch.no_grad()
def heldout_scores(field, state: Convergence) -> dict:
    """On the held-out probes of `state`: the training loss (without its consistency term), the
    language accuracy (the prediction at a mask's scale is nearest to that mask's embedding among the
    view's masks) and the instance accuracy (pairs closer than margin / 2 exactly when they share a group)."""
    c, loss, lang, inst = field.cfg, [], [], []
    for p in state.probes:
        K, tw, th, masks, scales, _, _ = field._train_view(p.kf)
        out = field._render(field.latents, K, p.kf.cam_to_world, tw, th, colour=False)
        targets = field.mapper.supervision.compressed(p.kf.index)
        f, l_lang, l_in = field._view_loss(out.channels.reshape(-1, c.latent_dim), p.pix, masks, scales,
                                           targets, p.own, p.sampled)
        loss.append(float(c.lambda_language * l_lang + c.lambda_instance * l_in))
        members = masks[:, p.pix].T  # [P, M]
        pi, mi = torch.nonzero(members, as_tuple=True)  # every (pixel, mask holding it)
        if len(pi):
            z = field.language_mlp(f[pi], field.scale_tf(scales[mi].double()))  # at each mask's own scale
            sim = torch.nn.functional.normalize(z, dim=1) @ torch.nn.functional.normalize(targets.float(), dim=1).T
            lang.append((sim[torch.arange(len(pi)), mi] >= sim.max(1).values - 1e-6).float())
        for s in p.sampled:
            feat = field.instance_mlp(f, field.scale_tf(s))
            share = shares_group(members, scales, s)
            close = torch.cdist(feat, feat) < c.margin / 2
            upper = torch.ones_like(share).triu(1)
            inst.append((close == share)[upper].float())
    mean = lambda xs: float(torch.cat(xs).mean()) if xs else float("nan")
    return {"loss": float(np.mean(loss)) if loss else float("nan"), "language": mean(lang), "instance": mean(inst)}


def check(field) -> dict | None:
    """Measure the held-out probes (every check_every steps); the stop decision once converged, else None."""
    with field.lock:
        field.sync()
        if field._refresh_supervision() is not None:
            return None
        return _check(field)


def _check(field) -> dict | None:
    c = field.cfg
    kfs = field._supervised()
    key = _key(field, kfs)
    st = field.convergence
    if st is None or st.key != key:
        pick = [kfs[int(i)] for i in np.unique(np.linspace(0, len(kfs) - 1, min(c.holdout_views, len(kfs))).round())]
        st = field.convergence = Convergence(key, field.steps, probes=[p for p in map(lambda kf: _probe(field, kf), pick) if p])
    if st.decision is not None:
        return st.decision
    n = field.steps - st.start
    if not st.probes or n % c.check_every or (st.history and st.history[-1][0] == n):
        return None
    sc = heldout_scores(field, st)
    st.history.append((n, field.seconds, (sc["language"] + sc["instance"]) / 2, sc["loss"], sc["language"], sc["instance"]))
    if n >= c.converge_min_steps and st.converged(c.converge_tol, c.converge_window):
        st.decision = {"stopped": "converged", "steps": field.steps, "seconds": round(field.seconds, 3),
                       "heldout": {k: round(v, 4) for k, v in sc.items()},
                       "rule": f"held-out accuracy gain < {100 * c.converge_tol:g} points over {c.converge_window} steps"}
    return st.decision


def train_until(field, seconds: float | None = None, iters: int | None = None, progress: bool = False,
                converge: bool | None = None, final: bool = True, until: Callable[[], bool] | None = None) -> dict:
    """FeatureField.train: train until `seconds` or `iters` runs out or, with the stop test on, the
    held-out accuracy converged. No budget given: cfg.steps steps if > 0, else up to cfg.seconds with
    the stop test (cfg.converge_tol > 0). An explicit budget is fixed unless `converge` is True.
    `until()` true before a step ends the call there ("interrupted": the node's service calls
    wait for one step, not a slice). Returns steps, seconds, mean losses, the budget and the stop
    decision (or why nothing ran). The decision is kept as `field.stop` (the field answers from then
    on) when converged or when the budget was `final`; a slice of a longer budget (the node's)
    passes final=False."""
    import sys

    from tqdm import tqdm

    if seconds is None and iters is None:
        iters, seconds = (field.cfg.steps, None) if field.cfg.steps > 0 else (None, field.cfg.seconds)
        converge = converge if converge is not None else field.cfg.steps == 0
    converge = bool(converge) and field.cfg.converge_tol > 0
    budget = {k: v for k, v in (("steps", iters), ("seconds", seconds)) if v is not None}
    t0, stop = time.perf_counter(), None
    hist, bar = [], tqdm(total=iters, desc="field", unit="it", disable=not progress, file=sys.stderr)
    while (iters is None or len(hist) < iters) and (seconds is None or time.perf_counter() - t0 < seconds):
        if converge and (stop := check(field)) is not None:
            break
        if until is not None and until():
            stop = {"stopped": "interrupted", "steps": field.steps, "seconds": round(field.seconds, 3)}
            break
        r = field.train_step()
        if "skipped" in r:
            bar.close()
            return {"steps": len(hist), "seconds": time.perf_counter() - t0, "skipped": r["skipped"],
                    "budget": budget}
        hist.append(r)
        bar.update(1)
        bar.set_postfix(loss=f"{r['loss']:.4f}")
    bar.close()
    if stop is None:
        stop = {"stopped": "steps" if iters is not None and len(hist) >= iters else "seconds",
                "steps": field.steps, "seconds": round(field.seconds, 3)}
    if (final and stop["stopped"] != "interrupted") or stop["stopped"] == "converged":
        field.stop = stop
    mean = lambda k: float(np.mean([h[k] for h in hist])) if hist else float("nan")
    return {"steps": len(hist), "seconds": time.perf_counter() - t0, "loss": mean("loss"),
            "language": mean("language"), "instance": mean("instance"), "budget": budget, "stop": stop,
            **({"curve": [list(h) for h in field.convergence.history]} if converge and field.convergence else {})}


def describe(decision: dict | None, steps_now: int | None = None) -> str:
    """One line for answers and logs: 'field: converged at 9.8 s, 312 steps, held-out accuracy gain < ...'
    (and how many steps it refined since, when `steps_now` is later)."""
    if not decision:
        return ""
    how = {"converged": "converged", "steps": "trained its step budget", "seconds": "trained its seconds budget"}.get(
        decision.get("stopped"), f"stopped ({decision.get('stopped')})")
    tail = f", {decision['rule']}" if decision.get("rule") else ""
    more = steps_now - decision["steps"] if steps_now is not None else 0
    return (f"field: {how} at {decision['seconds']:.1f} s, {decision['steps']} steps{tail}"
            + (f"; refined {more} steps since" if more > 0 else ""))
