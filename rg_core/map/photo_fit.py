"""A Gaussian map from posed photos without depth (issue 63): standard 3D Gaussian Splatting
optimisation (Kerbl et al. 2023) with the project's rasterizer, then the rendered depth stands in
for the sensor's, so supervision, the field and grounding run unchanged (the paper's order: a 3DGS
field first, features after).

- Initialisation: the sparse points (COLMAP points3D, points3d.ply) with 3DGS's scale rule (mean
  distance to the 3 nearest neighbours); a scene with poses but no points gets them triangulated at
  its poses (io/sfm.triangulate_posed, pycolmap); else `init_random` points in the cameras' frusta at
  depths within a factor 2 of the typical viewing distance (LLFF's bounds, else `world_depth`).
- Scene extent (the means' learning rate, the clone / split and prune sizes scale with it): 3DGS's
  1.1 x the cameras' spread, at least the typical viewing distance (near-static cameras).
- Loss: (1 - lambda) L1 + lambda D-SSIM (pytorch_msssim's SSIM, an 11 px Gaussian window) of the
  render composited over the learnt background.
- Adaptive density control: the mean view-space positional gradient (NDC units) of each Gaussian
  above `grad_threshold` clones the small ones and splits the large ones; low opacity (and, after
  the first opacity reset, a size above `prune_extent_share` of the scene) prunes; opacities are
  reset to 0.01 every `reset_opacity_every` steps while densifying. `max_gaussians` bounds it.
- Stop: a share of the views (`holdout_views`, evenly spaced) is held out whole, so the test measures
  novel views, not interpolation between trained pixels; their PSNR is measured every `check_every`
  steps, and once density control ended, the stop is decided when the best PSNR gained less than
  `converge_db` over `converge_window` steps, or at (1 - `join_share`) of the ceiling (step_ceiling:
  grows with the views). The held-out views then join for the last `join_share` of the steps.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ..config import MapConfig, PhotoMapConfig
from ..render.rasterize import rasterize
from .frames import map_camera
from .gaussians import PARAMS, GaussianModel, ResizableAdam
from .photo_losses import depth_smoothness, ssim


@dataclass
class PhotoView:
    """One posed photo at the working resolution."""

    rgb: torch.Tensor          # [H, W, 3] float32 in [0, 1]
    K: np.ndarray              # [3, 3]
    cam_to_world: np.ndarray   # [4, 4] OpenCV axes
    index: int = 0
    stamp: float = 0.0


@dataclass
class PhotoFit:
    """The fitted Gaussians and how the fit went: history rows (step, seconds, held-out PSNR dB,
    Gaussians), why it stopped, density-control counts."""

    gaussians: GaussianModel
    history: list = field(default_factory=list)
    stopped: str = ""
    steps: int = 0
    seconds: float = 0.0
    totals: dict = field(default_factory=dict)
    decided: int = 0                                   # step the stop was decided (then the held-out views joined)
    heldout: list = field(default_factory=list)        # indices of the views held out until then
    init: str = ""                                     # what the Gaussians started from
    depth_resolution: float = 0.0                      # m: depth a pixel of disparity spans (geometry.conventions)
    ceiling: int = 0                                   # step ceiling of this fit (step_ceiling)


def scene_extent(views: list[PhotoView], depth: float | None = None) -> float:
    """3DGS's scene radius: 1.1 x the largest distance of a camera centre from their mean, at least
    `depth` (the typical viewing distance: near-static cameras, a few mm apart, still see a scene a
    metre away, which the means must be able to move across), else at least 0.1."""
    c = np.stack([v.cam_to_world[:3, 3] for v in views])
    return float(max(1.1 * np.linalg.norm(c - c.mean(0), axis=1).max(), depth or 0.0, 0.1 if not depth else 0.0))


def viewing_depth(views: list[PhotoView], points: np.ndarray) -> float | None:
    """Median over the views of the median depth of the points in front of the camera and inside
    its image (None: no view sees any): the scene's typical viewing distance."""
    meds = []
    for v in views:
        w2c = np.linalg.inv(v.cam_to_world)
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        ok = z > 1e-6
        uv = cam[ok, :2] / z[ok, None] * v.K[[0, 1], [0, 1]] + v.K[:2, 2]
        h, w = v.rgb.shape[:2]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if inside.any():
            meds.append(float(np.median(z[ok][inside])))
    return float(np.median(meds)) if meds else None


def heldout_views(n: int, share: float) -> list[int]:
    """Indices of the views held out for the stop test: round(share x n) (at least 1 when share > 0
    and n >= 3, none otherwise) at the centres of n / k equal runs, so that they lie between
    trained views as test views do."""
    k = 0 if share <= 0 or n < 3 else min(max(1, round(share * n)), n - 2)
    return sorted({int((i + 0.5) * n / k) for i in range(k)}) if k else []


def initial_points(views: list[PhotoView], n: int, near: float, far: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(points [n, 3], colours [n, 3] in [0, 1]) drawn uniformly in the views' frusta between near
    and far: per point a view chosen uniformly, a pixel uniform in it and a depth uniform in inverse
    depth (so near space is not starved), coloured grey. Deterministic for a seeded `rng`."""
    which = rng.integers(len(views), size=n)                                  # [n] view of each point
    size = np.array([v.rgb.shape[1::-1] for v in views], np.float64)[which]   # [n, 2] (w, h)
    uv = rng.uniform(0.0, 1.0, (n, 2)) * size                                 # [n, 2] pixel
    z = 1.0 / rng.uniform(1.0 / far, 1.0 / near, n)                           # [n]
    K = np.stack([v.K for v in views])[which]                                 # [n, 3, 3]
    c2w = np.stack([v.cam_to_world for v in views])[which]                    # [n, 4, 4]
    xy = (uv - K[:, :2, 2]) / K[:, [0, 1], [0, 1]] * z[:, None]               # [n, 2] camera x, y
    cam = np.concatenate([xy, z[:, None]], 1)                                 # [n, 3]
    pts = np.einsum("nij,nj->ni", c2w[:, :3, :3], cam) + c2w[:, :3, 3]
    return pts.astype(np.float64), np.full((n, 3), 0.5)


def gaussians_from_points(points: np.ndarray, colors: np.ndarray, init_opacity: float = 0.1) -> GaussianModel:
    """Isotropic Gaussians at points [N, 3] with colours [N, 3] in [0, 1]; scale = mean distance to
    the 3 nearest other points (3DGS), floored so that duplicates never give a zero scale."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64)
    ok = np.isfinite(points).all(1)
    points, colors = points[ok], np.asarray(colors, np.float64)[ok]
    if len(points) < 4:
        raise ValueError(f"photo map: need at least 4 finite initial points, got {len(points)}")
    d, _ = cKDTree(points).query(points, k=4)
    s = np.sqrt(np.maximum((d[:, 1:] ** 2).mean(1), 1e-14))
    g = GaussianModel()
    g.append(torch.from_numpy(points).float(), torch.from_numpy(s).float(),
             torch.from_numpy(np.clip(colors, 0, 1)).float(), init_opacity)
    return g


def step_ceiling(cfg: PhotoMapConfig, views: int) -> int:
    """The fit's steps at most: min(iters, max(min_iters, steps_per_view x views)), or iters."""
    return min(cfg.iters, max(cfg.min_iters, cfg.steps_per_view * views)) if cfg.steps_per_view else cfg.iters


class PhotoFitter:
    """fit() runs the optimisation; one instance per map."""

    def __init__(self, views: list[PhotoView], cfg: PhotoMapConfig | None = None, map_cfg: MapConfig | None = None,
                 points: np.ndarray | None = None, colors: np.ndarray | None = None, depth_hint: float | None = None):
        if not views:
            raise ValueError("photo map: no views to fit")
        cfg = cfg or PhotoMapConfig()
        self.views, self.map_cfg = views, map_cfg or MapConfig()
        self.cfg = c = replace(cfg, iters=step_ceiling(cfg, len(views)))
        self.rng = np.random.default_rng(c.seed)
        self.gen = torch.Generator().manual_seed(c.seed)
        if points is None or len(points) < 4:
            d = depth_hint or c.world_depth   # no points: a band around the typical viewing distance
            self.depth = d
            points, colors = initial_points(views, c.init_random, max(self.map_cfg.near, d / 2), min(self.map_cfg.far, 2 * d),
                                            self.rng)
        else:
            self.depth = viewing_depth(views, np.asarray(points, np.float64)) or depth_hint
        self.extent = scene_extent(views, self.depth)
        self.g = gaussians_from_points(points, colors if colors is not None else np.full((len(points), 3), 0.5))
        self.optim = ResizableAdam(self.g, {"means": c.lr_means * self.extent, "log_scales": c.lr_scales,
                                            "quats": c.lr_quats, "opacity_logits": c.lr_opacity,
                                            "colors": c.lr_colors, "background": c.lr_colors})
        self.held = heldout_views(len(views), c.holdout_views)          # whole views kept for the stop test
        self.train_idx = [i for i in range(len(views)) if i not in set(self.held)]
        self.joined = not self.held                                     # held-out views trained on too
        self._grad = torch.zeros(len(self.g))
        self._seen = torch.zeros(len(self.g))
        self.totals = {"cloned": 0, "split": 0, "pruned": 0, "resets": 0}
        self.reset_done = False
        self.decided = 0

    def _render(self, v: PhotoView, params: dict):
        h, w = v.rgb.shape[:2]
        cam = map_camera(self.map_cfg, v.K, v.cam_to_world, w, h)
        out = rasterize(params["means"], torch.exp(params["log_scales"]), params["quats"],
                        torch.sigmoid(params["opacity_logits"]), params["colors"], cam,
                        antialiased=self.map_cfg.antialiased)
        rgb = out.channels + (1.0 - out.alpha)[..., None] * params["background"]
        return out, rgb

    def step(self, it: int) -> float:
        c = self.cfg
        pool = range(len(self.views)) if self.joined else self.train_idx
        v = self.views[pool[int(self.rng.integers(len(pool)))]]
        params = {k: t.detach().requires_grad_(True) for k, t in self.g.tensors().items()}
        out, rgb = self._render(v, params)
        m2d = out.projected.means2d if out.projected is not None else None
        if m2d is not None and m2d.requires_grad:
            m2d.retain_grad()
        l1 = (rgb - v.rgb).abs().mean()
        loss = (1 - c.lambda_dssim) * l1 + c.lambda_dssim * (1 - ssim(rgb, v.rgb))
        if c.depth_smoothness > 0:
            loss = loss + c.depth_smoothness * depth_smoothness(out.depth, out.alpha, v.rgb)
        loss.backward()
        decay = 0.01 ** min(1.0, it / max(c.iters, 1))                 # 3DGS: exponential to 1 %
        self.optim.lrs["means"] = c.lr_means * self.extent * decay
        self.optim.step({k: p.grad for k, p in params.items()})
        self.g.colors = self.g.colors.clamp(0.0, 1.0)
        if m2d is not None and m2d.grad is not None:
            h, w = v.rgb.shape[:2]
            gn = (m2d.grad * torch.tensor([w / 2.0, h / 2.0])).norm(dim=1)   # [N] NDC units
            seen = out.projected.radii > 0
            self._grad[seen] += gn[seen]
            self._seen[seen] += 1
        return float(loss.detach())

    def _densify_and_prune(self, densifying: bool) -> None:
        c, g = self.cfg, self.g
        if densifying:
            mean = self._grad / self._seen.clamp(min=1)
            big = g.scales.max(1).values > c.dense_share * self.extent
            hot = mean >= c.grad_threshold
            room = max(self.map_cfg.max_gaussians - len(g), 0)
            clone = torch.nonzero(hot & ~big).squeeze(1)
            split = torch.nonzero(hot & big).squeeze(1)
            if len(clone) + len(split) > room:   # the strongest gradients first
                order = torch.argsort(mean[torch.cat([clone, split])], descending=True)[:room]
                keep = torch.zeros(len(clone) + len(split), dtype=torch.bool)
                keep[order] = True
                clone, split = clone[keep[:len(clone)]], split[keep[len(clone):]]
            n0 = len(g)
            if len(clone):
                g.duplicate(clone)
            # split's indices still point at the original rows (duplicate appends at the end)
            if len(split):
                g.split(split, self.gen)
            self.totals["cloned"] += len(clone)
            self.totals["split"] += len(split)
            self._rebuild_optim(n0, clone, split)
        kill = g.opacities < c.prune_opacity
        if self.reset_done:
            kill |= g.scales.max(1).values > c.prune_extent_share * self.extent
        if kill.all():
            kill[torch.argmax(g.opacities)] = False   # never an empty map
        if kill.any():
            g.keep(~kill)
            self.optim.keep(~kill)
            self.totals["pruned"] += int(kill.sum())
        self._grad = torch.zeros(len(g))
        self._seen = torch.zeros(len(g))

    def _rebuild_optim(self, n0: int, clone: torch.Tensor, split: torch.Tensor) -> None:
        """Moments after clone (rows appended) and split (parents removed, children appended): the
        survivors keep theirs, new rows start at zero."""
        keep = torch.ones(n0 + len(clone), dtype=torch.bool)
        keep[split] = False
        self.optim.sync()        # grow to n0 + clones with zeros ...
        for k in PARAMS:         # ... then drop the split parents and grow for the children
            m, v = self.optim.m[k][: n0 + len(clone)], self.optim.v[k][: n0 + len(clone)]
            self.optim.m[k], self.optim.v[k] = m[keep], v[keep]
        self.optim.sync()

    @torch.no_grad()
    def heldout_psnr(self) -> float:
        """PSNR (dB) over the held-out views (nan without any)."""
        if not self.held:
            return float("nan")
        se, n = 0.0, 0
        params = self.g.tensors()
        for i in self.held:
            v = self.views[i]
            _, rgb = self._render(v, params)
            d = rgb.clamp(0, 1) - v.rgb
            se += float((d * d).sum())
            n += int(d.numel())
        mse = se / max(n, 1)
        return float("inf") if mse <= 0 else -10.0 * math.log10(mse)

    def fit(self, progress: bool = True) -> PhotoFit:
        from tqdm import tqdm

        c, t0 = self.cfg, time.perf_counter()
        until = int(c.densify_until * c.iters)
        decide = max(1, round((1 - c.join_share) * c.iters)) if self.held else c.iters   # the latest stop decision
        hist, stopped, it, end = [], "budget", 0, c.iters
        bar = tqdm(total=c.iters, desc="photo map", unit="step", disable=not progress, leave=False)
        for it in range(1, c.iters + 1):
            if it > end:
                break
            loss = self.step(it)
            if not math.isfinite(loss):
                raise FloatingPointError(f"photo map: loss is {loss} at step {it} (diverged)")
            densifying = c.densify_from <= it <= until
            if it % c.densify_every == 0 and it >= c.densify_from:
                self._densify_and_prune(densifying)
            if densifying and c.reset_opacity_every and it % c.reset_opacity_every == 0:
                self.g.opacity_logits = torch.minimum(self.g.opacity_logits, torch.full_like(self.g.opacity_logits,
                                                                                          math.log(0.01 / 0.99)))
                self.totals["resets"] += 1
                self.reset_done = True
            if not self.joined and (it % c.check_every == 0 or it == decide):
                p = self.heldout_psnr()
                hist.append((it, time.perf_counter() - t0, p, len(self.g)))
                bar.set_postfix(psnr=f"{p:.2f}", gaussians=len(self.g))
                conv = c.converge_db > 0 and it > until and self._converged(hist, until)
                if conv or it >= decide:   # decided: the held-out views join for the last join_share
                    stopped = "converged" if conv else "budget"
                    self.joined, self.decided = True, it
                    end = min(c.iters, it + math.ceil(it * c.join_share / max(1 - c.join_share, 1e-9)))
            bar.update(1)
        bar.close()
        return PhotoFit(self.g, hist, stopped, min(it, end), time.perf_counter() - t0, dict(self.totals),
                        decided=self.decided or min(it, end), heldout=list(self.held), ceiling=c.iters)

    def _converged(self, hist: list, until: int) -> bool:
        c = self.cfg
        after = [h for h in hist if h[0] > until]
        if not after or after[-1][0] - after[0][0] < c.converge_window:
            return False
        now = after[-1][0]
        best_before = max([h[2] for h in after if h[0] <= now - c.converge_window], default=-math.inf)
        best_now = max(h[2] for h in after)
        return best_now - best_before < c.converge_db


@torch.no_grad()
def rendered_depth(g: GaussianModel, v: PhotoView, map_cfg: MapConfig, min_alpha: float = 0.5) -> torch.Tensor:
    """[H, W] metres: the fitted map's expected depth where it is opaque (alpha >= min_alpha), else
    0 (invalid), what the supervision's physical scales then read as the sensor's depth."""
    h, w = v.rgb.shape[:2]
    cam = map_camera(map_cfg, v.K, v.cam_to_world, w, h)
    out = rasterize(g.means, g.scales, g.quats, g.opacities, g.colors, cam, antialiased=map_cfg.antialiased)
    return torch.where(out.alpha >= min_alpha, out.depth, torch.zeros_like(out.depth))


def photo_view(frame, width: int) -> PhotoView:
    """A scene Frame (io/scene.py) as a PhotoView at the working width (colour area-averaged, K
    rescaled): what the fit and the map's keyframes use."""
    import cv2

    from ..geometry.conventions import check_rigid, scale_intrinsics
    from .frames import working_size

    rgb = frame.load_rgb()
    H, W = rgb.shape[:2]
    w, h = working_size(W, H, width)
    if (w, h) != (W, H):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    c2w = np.asarray(frame.cam_to_world, np.float64)
    check_rigid(c2w, f"frame {frame.index} cam_to_world")
    return PhotoView(torch.from_numpy(rgb.astype(np.float32) / 255.0), scale_intrinsics(frame.intrinsics.K, w / W, h / H),
                     c2w, int(frame.index), float(frame.stamp))


def photo_mapper(frames, map_cfg: MapConfig | None = None, cfg: PhotoMapConfig | None = None, points=None,
                 progress: bool = True):
    """(Mapper, PhotoFit): the fit over `frames` (io Frames without depth), as a Mapper whose
    keyframes are those views (evenly thinned to map.max_keyframes) with the fit's rendered depth,
    so supervision, the field, grounding and saving run unchanged. `points`: io.scene.SparsePoints
    or None (random initialisation)."""
    from ..geometry.conventions import depth_resolution
    from .keyframes import Keyframe
    from .mapper import Mapper
    from .gaussians import ResizableAdam

    map_cfg = map_cfg or MapConfig()
    views = [photo_view(f, map_cfg.width) for f in frames]
    for i, v in enumerate(views):   # a keyframe's index is its position in the input stream, as the Mapper's
        v.index = i
    cfg = cfg or PhotoMapConfig()
    if (points is None or len(points.xyz) < 4) and cfg.triangulate:   # poses but no points: triangulate them
        from ..io.sfm import triangulate_posed

        points = triangulate_posed(frames, min_angle_deg=cfg.triangulate_min_angle)
    xyz = rgb = None
    if points is not None and len(points.xyz) >= 4:
        xyz, rgb = points.xyz, np.asarray(points.rgb, np.float64) / 255.0
    bounds = [math.sqrt(max(f.bounds[0], 1e-9) * f.bounds[1]) for f in frames if getattr(f, "bounds", None)]
    fit = PhotoFitter(views, cfg, map_cfg, xyz, rgb, float(np.median(bounds)) if bounds else None).fit(progress=progress)
    fit.init = points.source if xyz is not None and points is not None else f"{cfg.init_random} random"
    m = Mapper(map_cfg)
    m.gaussians = fit.gaussians
    m.optim = ResizableAdam(m.gaussians, m.optim.lrs)   # refinement and the node continue from here
    keep = views
    if map_cfg.max_keyframes and len(views) > map_cfg.max_keyframes:
        keep = [views[i] for i in np.linspace(0, len(views) - 1, map_cfg.max_keyframes).round().astype(int)]
    m.keyframes = [Keyframe(v.index, v.stamp, v.cam_to_world, v.K, v.rgb, rendered_depth(fit.gaussians, v, map_cfg))
                   for v in keep]
    z = torch.cat([kf.depth[kf.depth > 0] for kf in m.keyframes])                     # the map's depths
    fit.depth_resolution = depth_resolution(np.stack([v.K for v in views]), np.stack([v.cam_to_world for v in views]),
                                            float(z.median()) if len(z) else 0.0)
    m.frames_seen = len(frames)
    m.last_stamp = max(v.stamp for v in views)
    m.totals["added"] = len(fit.gaussians)
    m.totals["split"], m.totals["pruned"] = fit.totals["split"], fit.totals["pruned"]
    m.seconds["optimise"] = fit.seconds
    return m, fit


def fit_summary(fit: PhotoFit) -> dict:
    """What a report says of a fit: steps, why it stopped, seconds, Gaussians, density control and
    the held-out PSNR against time (the curve `rg report` plots)."""
    return {"steps": fit.steps, "ceiling": fit.ceiling, "stopped": fit.stopped, "decided": fit.decided,
            "heldout_views": fit.heldout, "init": fit.init, "depth_resolution_m": round(fit.depth_resolution, 5),
            "seconds": round(fit.seconds, 3),
            "gaussians": len(fit.gaussians), **fit.totals,
            "heldout_psnr": [[h[0], round(h[1], 3), round(h[2], 3), h[3]] for h in fit.history]}
