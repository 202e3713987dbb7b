"""Incremental Gaussian mapping from posed RGB-D frames (no ROS; the node feeds it frames).

Per frame: render the map from the frame's pose; pixels the map does not explain (low alpha or
depth error) decide whether the frame is a keyframe; a keyframe seeds Gaussians only there and is
optimised with a window of keyframes for an iteration budget, its first iterations at half resolution
(coarse to fine); then transparent, oversized or broken Gaussians are pruned. The map stays under
`max_gaussians`: at the bound, new seeds replace the least useful Gaussians (`evict`).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..config import MapConfig
from ..render import EPS2D, Camera, RenderOutput, rasterize
from .frames import PreparedFrame, map_camera, prepare_frame
from .gaussians import GaussianModel, ResizableAdam
from .keyframes import Keyframe, keyframe_reason, most_redundant, same_view
from .removal import eviction_order, protected_box, prune_keep
from .taught import TaughtSet
from .seeding import back_project, coarse_gaussians, detail_pixels, local_range, seed_candidates

log = logging.getLogger(__name__)


@dataclass
class FrameResult:
    """What add_frame did with one frame."""

    keyframe: bool
    reason: str
    added: int = 0
    dropped: int = 0            # seeds not added because of max_gaussians
    pruned: int = 0
    unexplained: float = 0.0    # fraction of valid depth pixels the map did not explain
    photometric_error: float = 0.0
    replaced: int | None = None  # index of the keyframe this one replaced (same view: MapConfig.kf_revisit)
    revisit: int | None = None   # the unchanged keyframe this frame revisited (seeded, not a keyframe)
    seconds: dict = field(default_factory=dict)


@dataclass
class _Passes:
    """Where the converging refinement is: the map it runs on (frames seen, evicted, keyframes), the
    current pass's order and position, its summed loss, the last full pass's mean loss."""
    key: tuple
    order: list = field(default_factory=list)
    pos: int = 0
    loss: float = 0.0
    prev: float | None = None
    passes: int = 0
    converged: bool = False


class Mapper:
    def __init__(self, cfg: MapConfig | None = None):
        self.cfg = cfg or MapConfig()
        self.gaussians = GaussianModel()
        self.keyframes: list[Keyframe] = []
        lr = self.cfg
        self.optim = ResizableAdam(self.gaussians, {
            "means": lr.lr_means, "log_scales": lr.lr_scales, "quats": lr.lr_quats,
            "opacity_logits": lr.lr_opacity, "colors": lr.lr_colors, "background": lr.lr_colors})
        self.frames_seen = 0
        self.last_stamp: float | None = None
        self.totals = {"added": 0, "dropped": 0, "pruned": 0, "evicted": 0, "out_of_order": 0, "keyframe_iters": 0,
                       "keyframes_dropped": 0, "keyframes_replaced": 0, "revisits": 0, "split": 0}
        self.protected: list[tuple[np.ndarray, np.ndarray]] = []   # boxes (lo, hi) eviction never touches
        self.seconds = {"prepare": 0.0, "check": 0.0, "seed": 0.0, "optimise": 0.0, "prune": 0.0, "refine": 0.0}
        self._rng = torch.Generator().manual_seed(self.cfg.seed)
        self.supervision = None  # perception.supervision.SupervisionSet, once computed
        self.taught = TaughtSet()  # objects people named (grounding/teach.py); eviction keeps them
        self.built: dict = {}  # how the map was made (map.run.build_map: kind, world scale, photo fit), saved with it
        self._passes: _Passes | None = None  # the converging refinement's passes, for `refine(resume=True)`

    # ------------------------------------------------------------------------------ rendering

    def camera(self, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int) -> Camera:
        return map_camera(self.cfg, K, cam_to_world, width, height)

    def render(self, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
               subset: torch.Tensor | None = None, return_ids: bool = False, background: bool = False) -> RenderOutput:
        """Render colour, depth and alpha of the map; `background` composites the map's learnt
        background colour where alpha < 1 (a picture), otherwise uncovered pixels stay black."""
        g = self.gaussians
        return rasterize(g.means, g.scales, g.quats, g.opacities, g.colors, self.camera(K, cam_to_world, width, height),
                         subset=subset, return_ids=return_ids, background=g.background if background else None,
                         antialiased=self.cfg.antialiased)

    # ------------------------------------------------------------------------------ ingestion

    def add_frame(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray,
                  stamp: float) -> FrameResult:
        """Ingest one frame: rgb [H, W, 3] uint8, depth [H, W] float metres (0/NaN invalid),
        K [3, 3], cam_to_world [4, 4] (OpenCV axes). Raises FrameError (map untouched) on bad input."""
        t0 = time.perf_counter()
        fr = prepare_frame(rgb, depth, K, cam_to_world, stamp, self.cfg.width)  # raises before any change
        t1 = time.perf_counter()
        self.seconds["prepare"] += t1 - t0
        if self.last_stamp is not None and fr.stamp < self.last_stamp:
            self.totals["out_of_order"] += 1
            n = self.totals["out_of_order"]
            if n == 1 or n % 100 == 0:  # rate-limited: a replayed bag must not flood the log
                log.warning("frame stamp %.6f is older than the last one (%.6f): accepted (%d such frames so far)",
                            fr.stamp, self.last_stamp, n)
        self.last_stamp = fr.stamp if self.last_stamp is None else max(self.last_stamp, fr.stamp)
        index = self.frames_seen
        self.frames_seen += 1

        rgb_t = torch.from_numpy(fr.rgb)
        depth_t = torch.from_numpy(fr.depth)
        valid = depth_t > 0
        h, w = depth_t.shape
        with torch.no_grad():
            if len(self.gaussians):
                out = self.render(fr.K, fr.cam_to_world, w, h)
                unexplained = self._unexplained(out, depth_t, valid)
                explained = valid & ~unexplained
                photo = float((out.channels - rgb_t).abs().mean(-1)[explained].mean()) if explained.any() else 1.0
            else:
                unexplained, photo = valid.clone(), 1.0
        frac = float(unexplained.sum()) / max(int(valid.sum()), 1)
        t2 = time.perf_counter()
        self.seconds["check"] += t2 - t1
        reason, is_keyframe, near_static = keyframe_reason(self.keyframes, self.cfg, fr.stamp, frac, photo)
        res = FrameResult(is_keyframe, reason, unexplained=frac, photometric_error=photo)
        if not is_keyframe:
            res.seconds = {"prepare": t1 - t0, "check": t2 - t1}
            return res
        kf = Keyframe(index, fr.stamp, fr.cam_to_world, fr.K, rgb_t, depth_t)
        near = None
        if self.keyframes and self.cfg.kf_revisit > 0 and not near_static:
            near = same_view(self.keyframes, kf, self.cfg.kf_revisit)
        if near is not None:
            j, d, changed = near
            old = self.keyframes[j]
            if changed <= self.cfg.kf_new_fraction:   # the same view, unchanged: only the map lacks it
                res.keyframe, res.revisit = False, old.index   # seeded and optimised below, not added
                self.totals["revisits"] += 1
                res.reason += (f"; a revisit of keyframe {old.index} ({d:.3f} m-equivalent, "
                               f"{100 * changed:.1f}% changed): its unexplained pixels seeded, no new keyframe")
            else:
                self._remove_keyframe(j)
                res.replaced = old.index
                self.totals["keyframes_replaced"] += 1
                res.reason += (f"; replaces keyframe {old.index} at the same view ({d:.3f} m-equivalent, "
                               f"{100 * changed:.1f}% changed)")
        if res.keyframe:
            while self.cfg.max_keyframes and len(self.keyframes) >= self.cfg.max_keyframes:
                if self.drop_redundant_keyframe() is None:     # room first: the count never passes the budget
                    break
            self.keyframes.append(kf)
        res.added, res.dropped = self._seed(fr, unexplained)
        t3 = time.perf_counter()
        self.totals["keyframe_iters"] += self._optimise(self.cfg.iters_per_keyframe, converge=True)
        if res.keyframe and self.cfg.seed_colour_error > 0:
            a, d = self._densify(fr, kf)
            res.added, res.dropped = res.added + a, res.dropped + d
        t4 = time.perf_counter()
        res.pruned = self._prune()
        while self.cfg.max_keyframes and len(self.keyframes) > self.cfg.max_keyframes:
            if self.drop_redundant_keyframe() is None:
                break
        t5 = time.perf_counter()
        for k, dt in (("seed", t3 - t2), ("optimise", t4 - t3), ("prune", t5 - t4)):
            self.seconds[k] += dt
        res.seconds = {"prepare": t1 - t0, "check": t2 - t1, "seed": t3 - t2, "optimise": t4 - t3, "prune": t5 - t4}
        self.totals["added"] += res.added
        self.totals["dropped"] += res.dropped
        self.totals["pruned"] += res.pruned
        return res

    def depth_tolerance(self, depth: torch.Tensor) -> torch.Tensor:
        """[h, w] metres: how far a rendered depth may lie from a reading `depth` [h, w] and still
        explain it, max(depth_error_abs, depth_error_rel x depth)."""
        return torch.clamp(depth * self.cfg.depth_error_rel, min=self.cfg.depth_error_abs)

    def _unexplained(self, out: RenderOutput, depth: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        c = self.cfg
        err = (out.depth - depth).abs()
        tol = self.depth_tolerance(depth)
        # Within one seed footprint of a depth discontinuity the rendered (expected) depth blends
        # both surfaces: the depth test is meaningless there, only coverage (alpha) counts.
        near_edge = local_range(depth, 2 * c.seed_stride + 1, valid) > tol
        return valid & ((out.alpha < c.unexplained_alpha) | ((err > tol) & ~near_edge))

    def _seed(self, fr: PreparedFrame, unexplained: torch.Tensor, depth: torch.Tensor | None = None,
              stride: int | None = None) -> tuple[int, int]:
        """Back-project unexplained depth pixels (one per stride x stride block, seeding.seed_candidates)
        as new Gaussians; `depth` [h, w] (default the frame's sensor depth) places them. With the default
        stride and `seed_spacing`, surfaces so far that a block spans more than it are seeded at half
        the stride. At max_gaussians, eviction makes room, else a random share is dropped."""
        c = self.cfg
        depth = torch.from_numpy(fr.depth) if depth is None else depth              # [h, w] metres
        vs, us, strides = seed_candidates(unexplained, depth, float(fr.K[0, 0]), stride or c.seed_stride,
                                          c.seed_spacing if stride is None else 0.0)
        n_cand = len(vs)
        room = max(c.max_gaussians - len(self.gaussians), 0)
        if n_cand > room and c.evict:
            room += self.evict(min(n_cand, c.max_gaussians) - room, fr.K, fr.cam_to_world, *unexplained.shape[::-1])
        if n_cand > room:
            pick = torch.randperm(n_cand, generator=self._rng)[:room].sort().values
            vs, us, strides = vs[pick], us[pick], strides[pick]
        if len(vs) == 0:
            return 0, n_cand
        means, scales = back_project(vs, us, strides, depth, fr.K, fr.cam_to_world, c.seed_scale)
        self.gaussians.append(means.float(), scales.float(), torch.from_numpy(fr.rgb)[vs, us], c.init_opacity)
        self.optim.sync()
        return len(vs), n_cand - len(vs)

    @torch.no_grad()
    def _densify(self, fr: PreparedFrame, kf: Keyframe) -> tuple[int, int]:
        """Detail the map still lacks after optimising a keyframe: where it renders the right surface
        in the wrong colour (L1 above `seed_colour_error`, seeding.detail_pixels), split the coarse
        Gaussians drawing it (`split_px`) and seed at half the stride, placed by the sensor depth or,
        where the sensor has none, by the map's own rendered surface."""
        w, h = kf.size
        out = self.render(kf.K, kf.cam_to_world, w, h, return_ids=True)
        depth, detail = detail_pixels(out, kf.rgb, kf.depth, self.gaussians.background, self.cfg.seed_colour_error)
        if self.cfg.split_px > 0 and detail.any():
            self._split_coarse(out.ids[detail], kf)
        return self._seed(fr, detail, depth, max(1, self.cfg.seed_stride // 2))

    def _split_coarse(self, ids: torch.Tensor, kf: Keyframe) -> int:
        """Split (GaussianModel.split) the Gaussians ids [M] (-1: none) whose largest axis spans more than
        `split_px` pixels in keyframe kf: a coarse Gaussian that draws detail pixels in the wrong
        colour. Sorted by its centre's depth, it also hides the detail's own Gaussians behind it (a
        knife on a table under one big table Gaussian). A split adds one Gaussian: under
        max_gaussians only the widest split. Returns how many were split."""
        g = self.gaussians
        ids = torch.unique(ids[ids >= 0])
        if not len(ids):
            return 0
        big = coarse_gaussians(g.means, g.scales, ids, kf.K, kf.cam_to_world, self.cfg.near, self.cfg.split_px,
                               max(self.cfg.max_gaussians - len(g), 0))
        keep = torch.ones(len(g), dtype=torch.bool)
        keep[big] = False
        g.split(big, self._rng)
        self.optim.keep(keep)     # the parents' moments go; the children's start at zero
        self.optim.sync()
        self.totals["split"] += len(big)
        return len(big)

    def refine(self, iters: int, converge: bool = True, resume: bool = False) -> float:
        """Optimise over all keyframes (what a robot does when idle, and `rg map` at the end of a
        run: `final_iters`), drawn uniformly; with `converge` and cfg.refine_tol > 0 in passes that
        visit every keyframe once, in random order, stopping once a pass lowered the mean loss by
        less than refine_tol against the pass before. `resume`: go on with the passes of the last
        call while no frame came and nothing was evicted (a node refines in short slices; once
        converged, a slice does nothing: past convergence the Gaussians only grow, see
        docs/pipeline.md). Then prune. Returns seconds."""
        t, c = time.perf_counter(), self.cfg
        if self.keyframes and iters > 0:
            n, done = len(self.keyframes), 0
            if not (converge and c.refine_tol > 0):  # a fixed budget, uniform draws
                for _ in range(iters):
                    self._step(self.keyframes[int(torch.randint(0, n, (1,), generator=self._rng))])
                self.last_refine = {"iters": iters, "of": iters, "stopped": "budget"}
            else:
                key = (self.frames_seen, self.totals["evicted"], tuple(k.index for k in self.keyframes))
                st = self._passes if resume and self._passes is not None and self._passes.key == key else _Passes(key)
                self._passes = st
                while done < iters and not st.converged:
                    if st.pos == len(st.order):
                        st.order, st.pos = torch.randperm(n, generator=self._rng).tolist(), 0
                    st.loss += self._step(self.keyframes[st.order[st.pos]])
                    st.pos, done = st.pos + 1, done + 1
                    if st.pos == n:       # a full pass
                        mean, st.passes, st.loss = st.loss / n, st.passes + 1, 0.0
                        st.converged = (st.prev is not None and st.passes >= c.refine_min_passes
                                        and st.prev - mean < c.refine_tol * st.prev)
                        st.prev = mean
                self.last_refine = {"iters": done, "passes": st.passes, "of": iters,
                                    "stopped": "converged" if st.converged else "budget"}
            self.totals["pruned"] += self._prune()
        dt = time.perf_counter() - t
        self.seconds["refine"] = self.seconds.get("refine", 0.0) + dt
        return dt

    def _sample_keyframe(self) -> Keyframe:
        n = len(self.keyframes)
        r = float(torch.rand(1, generator=self._rng))
        if r < 0.4 or n == 1:
            return self.keyframes[-1]
        if r < 0.8:
            lo = max(0, n - self.cfg.window)
            return self.keyframes[int(torch.randint(lo, n, (1,), generator=self._rng))]
        return self.keyframes[int(torch.randint(0, n, (1,), generator=self._rng))]

    def _optimise(self, iters: int, converge: bool = False) -> int:
        """Up to `iters` steps over sampled keyframes, the first coarse_share of them at coarse_scale;
        with `converge` and cfg.converge_tol > 0 the full-resolution ones stop once their windowed loss
        stops falling (see MapConfig). Returns the steps run."""
        c = self.cfg
        coarse = round(c.coarse_share * iters)
        for _ in range(coarse):
            kf = self._sample_keyframe()
            if kf.size[0] * c.coarse_scale >= c.coarse_min_width:
                self._step(kf.at_scale(c.coarse_scale), c.coarse_scale)
            else:
                self._step(kf)
        win, losses = c.converge_window, []
        for _ in range(iters - coarse):
            losses.append(self._step(self._sample_keyframe()))
            if converge and c.converge_tol > 0 and len(losses) >= 2 * win:
                prev, last = sum(losses[-2 * win:-win]) / win, sum(losses[-win:]) / win
                if prev - last < c.converge_tol * prev:
                    break
        return coarse + len(losses)

    def _step(self, kf: Keyframe, scale: float = 1.0) -> float:
        """One optimisation step on one keyframe at `scale` of the working resolution (Keyframe.at_scale);
        returns its loss. The renderer's low-pass filter (EPS2D px^2) shrinks with the pixel area, so it
        blurs the same in the world at every scale (else coarse steps grow the Gaussians' footprints)."""
        g, c = self.gaussians, self.cfg
        w, h = kf.size
        params = {k: v.detach().requires_grad_(True) for k, v in g.tensors().items()}
        cam = self.camera(kf.K, kf.cam_to_world, w, h)
        out = rasterize(params["means"], torch.exp(params["log_scales"]), params["quats"],
                        torch.sigmoid(params["opacity_logits"]), params["colors"], cam, eps2d=EPS2D * scale * scale,
                        antialiased=c.antialiased)
        valid = kf.depth > 0
        nv = valid.sum().clamp(min=1)
        # Colour: the whole image against the render composited over the learnt background
        # (Gaussians grow into depth holes; pixels no Gaussian reaches teach the background).
        rgb = out.channels + (1.0 - out.alpha)[..., None] * params["background"]
        l_rgb = (rgb - kf.rgb).abs().mean()
        l_depth = ((out.depth - kf.depth).abs() * valid).sum() / nv
        l_alpha = ((1.0 - out.alpha) * valid).sum() / nv
        loss = l_rgb + c.lambda_depth * l_depth + c.lambda_alpha * l_alpha
        if c.lambda_opacity > 0:
            loss = loss + c.lambda_opacity * torch.sigmoid(params["opacity_logits"]).mean()
        loss.backward()
        self.optim.step({k: p.grad for k, p in params.items()})
        g.colors = g.colors.clamp(0.0, 1.0)   # what a camera sees: no darkening through the wrong Gaussian
        return float(loss.detach())

    def protect(self, lo: np.ndarray, hi: np.ndarray, margin: float = 0.02, keep_last: int = 16) -> None:
        """Never evict the Gaussians inside the box lo..hi [3] (+ margin, metres): e.g. an object that
        was just grounded. The last `keep_last` boxes are kept."""
        self.protected = (self.protected + [protected_box(lo, hi, margin)])[-keep_last:]

    @torch.no_grad()
    def evict(self, n: int, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int) -> int:
        """Remove up to `n` Gaussians the camera (K [3, 3], cam_to_world [4, 4], image size) does not
        see, the least useful first (removal.eviction_order); Gaussians in view, in protected
        boxes and in taught objects' boxes stay. Returns how many went."""
        g = self.gaussians
        if n <= 0 or not len(g):
            return 0
        order = eviction_order(g, n, K, cam_to_world, width, height, self.cfg.near,
                               self.protected + self.taught.boxes())
        if not len(order):
            return 0
        keep = torch.ones(len(g), dtype=torch.bool)
        keep[order] = False
        g.keep(keep)
        self.optim.keep(keep)
        self.totals["evicted"] = self.totals.get("evicted", 0) + len(order)
        return len(order)

    def drop_redundant_keyframe(self, metres_per_radian: float = 0.3) -> Keyframe | None:
        """Drop the keyframe whose view another keyframe covers best (keyframes.most_redundant: the
        newest `window` and the last one stay). Its supervision goes with it; its Gaussians stay.
        Returns it (None: none could go)."""
        victim = most_redundant(self.keyframes, self.cfg.window, metres_per_radian)
        return None if victim is None else self._remove_keyframe(victim)

    def _remove_keyframe(self, i: int) -> Keyframe:
        """Take keyframe i out with its supervision (its Gaussians stay); counted as dropped."""
        kf = self.keyframes.pop(i)
        if self.supervision is not None:
            self.supervision.remove(kf.index)
        self.totals["keyframes_dropped"] = self.totals.get("keyframes_dropped", 0) + 1
        return kf

    def _prune(self) -> int:
        """Remove transparent, oversized and broken Gaussians (removal.prune_keep); returns how many."""
        g, c = self.gaussians, self.cfg
        if not len(g):
            return 0
        keep = prune_keep(g, c.prune_opacity, c.prune_scale)
        n = int((~keep).sum())
        if n:
            g.keep(keep)
            self.optim.keep(keep)
        return n

    # ------------------------------------------------------------------------------ summary

    def stats(self) -> dict:
        return {"frames": self.frames_seen, "keyframes": len(self.keyframes), "gaussians": len(self.gaussians),
                **{k: int(v) for k, v in self.totals.items()},
                "seconds": {k: round(v, 3) for k, v in self.seconds.items()}}
