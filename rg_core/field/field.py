"""FeatureField: a latent f in R^latent_dim per Gaussian of a Mapper's map, rendered with colour and
depth in one rasterizer call, decoded by F_l(s, f) (language, PCA space) and F_g(s, f) (instance).

Geometry and colour stay frozen: only latents and the two mappers train. Training is incremental
and safe to call from a background thread between map updates: each step first follows the map
(new Gaussians start from their nearest neighbours' latents; pruning re-associates by centre),
the supervision (new keyframes; scale transform refits) and the PCA basis (a refit re-expresses
the language mapper's output layer exactly in the new basis).
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..config import FieldConfig
from ..geometry.conventions import scale_intrinsics
from ..geometry.points import nearest
from ..render import frustum_cull, rasterize
from .converge import train_until
from .losses import instance_loss, language_loss, language_targets, shares_group
from .mappers import ScaleMLP, sparse_adam_step
from .sampling import sample_keyframe, sample_scale, training_view
from .scale import QuantileScale

_MOVED = 1e-3  # m: on re-association after pruning, a Gaussian this close to an old one is that one


@dataclass
class FieldRender:
    latent: torch.Tensor   # [h, w, latent_dim] alpha-blended latents (no background)
    rgb: torch.Tensor      # [h, w, 3] (no background)
    depth: torch.Tensor    # [h, w] expected depth (m), 0 where nothing was hit
    alpha: torch.Tensor    # [h, w]


class FeatureField:
    """Attaches itself as `mapper.field`, so `save_map` stores it with the map."""

    def __init__(self, mapper, cfg: FieldConfig | None = None):
        self.mapper, self.cfg = mapper, cfg or FieldConfig()
        c = self.cfg
        if c.latent_dim < 1 or c.rays_per_step < 2 or c.scales_per_step < 1 or c.train_width < 8:
            raise ValueError(f"FieldConfig: latent_dim >= 1, rays_per_step >= 2, scales_per_step >= 1 and "
                             f"train_width >= 8 needed, got {c}")
        self.lock = threading.RLock()  # one step, render or resize at a time
        self._rng = torch.Generator().manual_seed(c.seed)
        with torch.random.fork_rng():
            torch.manual_seed(c.seed)
            self.language_mlp = ScaleMLP(c.latent_dim, c.language_dim, c.hidden, c.scale_frequencies)
            self.instance_mlp = ScaleMLP(c.latent_dim, c.instance_dim, c.hidden, c.scale_frequencies, unit=True)
        self._mlp_optim = None  # made on the first training step: torch.optim imports torch._dynamo (seconds)
        n = len(mapper.gaussians)
        self.latents = torch.randn(n, c.latent_dim, generator=self._rng) * c.init_std  # [N, D]
        self._m, self._v = torch.zeros(n, c.latent_dim), torch.zeros(n, c.latent_dim)
        self._t = torch.zeros(n, dtype=torch.long)  # per-row Adam step count (rows update sparsely)
        self._spare: dict[str, torch.Tensor] = {}  # row tensor name -> its storage with room to grow
        self._means = mapper.gaussians.means.detach().clone()  # centres at the last sync
        self._pruned = self._pruned_count()
        self.scale_tf: QuantileScale | None = None
        self._pca = None  # (version, mean, components) the language output is expressed in
        self._masks: dict[int, tuple] = {}  # kf -> (sup, masks [M, th tw], scales [M], ray weights [th tw])
        self.steps, self.seconds = 0, 0.0
        self.revision = 0  # bumped whenever an existing row's output can change (training, pruning, scale refit);
        #                    appending rows for new Gaussians keeps it, so per-row results of old rows stay valid
        self.convergence = None  # converge.Convergence: the stop test on the current supervision
        self.stop: dict | None = None  # how the last train() ended (converge.describe says it in words)
        mapper.field = self

    @property
    def mlp_optim(self):
        """Adam over both mappers' weights, made when training first needs it (a map loaded only to
        answer queries never does, and a new process saves the seconds torch.optim's import takes)."""
        if self._mlp_optim is None:
            self._mlp_optim = torch.optim.Adam(list(self.language_mlp.parameters()) + list(self.instance_mlp.parameters()),
                                               lr=self.cfg.lr_mappers)
        return self._mlp_optim

    # ---------------------------------------------------------------------------- map following

    def _pruned_count(self):
        """Gaussians removed from the map so far (pruned or evicted), None when unknown."""
        t = getattr(self.mapper, "totals", {})
        return None if "pruned" not in t else t["pruned"] + t.get("evicted", 0)

    def _neighbour_latents(self, points: torch.Tensor) -> torch.Tensor:  # [Q, 3] -> [Q, D]
        k = min(self.cfg.init_neighbours, len(self._means))
        if k < 1:
            return torch.randn(len(points), self.cfg.latent_dim, generator=self._rng) * self.cfg.init_std
        _, idx = nearest(self._means.numpy(), points.numpy(), k)
        return self.latents[torch.from_numpy(idx)].mean(1)

    def _append_rows(self, name: str, rows: torch.Tensor) -> None:
        """Append rows to the [N, ...] tensor `name` in spare capacity (grown 1.25x when full), so a
        map growing by a frame's Gaussians does not copy every old row each time."""
        cur = getattr(self, name)
        n, k = len(cur), len(rows)
        base = self._spare.get(name)
        if base is None or base.data_ptr() != cur.data_ptr() or len(base) < n + k:
            base = torch.empty((max(n + k, int(1.25 * (n + k))),) + tuple(cur.shape[1:]), dtype=cur.dtype)
            base[:n] = cur
            self._spare[name] = base
        base[n:n + k] = rows
        setattr(self, name, base[:n + k])

    @torch.no_grad()
    def sync(self) -> int:
        """Follow the map's Gaussians; returns how many latents were (re)initialised. Appends keep
        every old row; after pruning, rows are re-associated with the old Gaussian at the same centre."""
        with self.lock:
            g = self.mapper.gaussians
            N, old = len(g), len(self.latents)
            pruned = self._pruned_count()
            means = g.means.detach()
            if N == old and pruned == self._pruned and pruned is not None:
                self._means = means.clone()
                return 0
            D = self.cfg.latent_dim
            if pruned is not None and pruned == self._pruned and N > old:  # append-only: rows kept
                self._append_rows("latents", self._neighbour_latents(means[old:]))
                z = torch.zeros(N - old, D)
                self._append_rows("_m", z)
                self._append_rows("_v", z)
                self._append_rows("_t", torch.zeros(N - old, dtype=torch.long))
                fresh = N - old
            else:  # pruned (rows shifted) or unknown history: re-associate by centre
                from scipy.spatial import cKDTree

                lat, m, v, t = (torch.zeros(N, D), torch.zeros(N, D), torch.zeros(N, D),
                                torch.zeros(N, dtype=torch.long))
                fresh = N
                if old and N:
                    d, j = cKDTree(self._means.double().numpy()).query(means.double().numpy(), k=1)
                    same = torch.from_numpy(d <= _MOVED)
                    j = torch.from_numpy(np.asarray(j, np.int64))
                    lat[same], m[same], v[same], t[same] = (self.latents[j[same]], self._m[j[same]],
                                                            self._v[j[same]], self._t[j[same]])
                    fresh = int((~same).sum())
                    if fresh:
                        lat[~same] = self._neighbour_latents(means[~same])
                elif N:
                    lat = self._neighbour_latents(means)
                self.latents, self._m, self._v, self._t = lat, m, v, t
                self.revision += 1
            self._means, self._pruned = means.clone(), pruned
            return fresh

    # ---------------------------------------------------------------------------- supervision

    def _supervised(self) -> list:
        sset = getattr(self.mapper, "supervision", None)
        if sset is None:
            return []
        for k in set(self._masks) - {kf.index for kf in self.mapper.keyframes}:
            del self._masks[k]          # a dropped keyframe (MapConfig.max_keyframes)
        return [kf for kf in self.mapper.keyframes
                if kf.index in sset.by_keyframe and len(sset.by_keyframe[kf.index].scales)]

    def _refresh_supervision(self) -> str | None:
        """Refit the scale transform when supervision grew 1.5x; follow a PCA refit. Returns why
        training cannot run, or None."""
        sset = getattr(self.mapper, "supervision", None)
        kfs = self._supervised()
        if not kfs:
            return "no keyframe has supervision masks yet"
        if sset.pca.pca is None:
            return "PCA of the mask embeddings not fitted yet (too few masks)"
        scales = np.concatenate([sset.by_keyframe[kf.index].scales for kf in kfs])
        if self.scale_tf is None or len(scales) >= 1.5 * self.scale_tf.n_fit:
            self.scale_tf = QuantileScale.fit(torch.from_numpy(scales.astype(np.float64)), self.cfg.scale_knots)
            self.revision += 1
        self._follow_pca(sset.pca)
        return None

    def follow_supervision(self) -> None:
        """Follow a changed supervision now (a PCA refit, relabelled masks): queries read the
        language output in the map's current basis before the next training step."""
        with self.lock:
            self._refresh_supervision()

    @torch.no_grad()
    def _follow_pca(self, ipca) -> None:
        """Re-express the language output layer in a refitted basis: z' = C'(C^T z + mu - mu')."""
        pca = ipca.pca
        if pca.dim != self.cfg.language_dim:
            raise ValueError(f"field: PCA has {pca.dim} dims, FieldConfig.language_dim is {self.cfg.language_dim}")
        if self._pca is not None and self._pca[0] != ipca.version:
            _, mean, comps = self._pca
            last = self.language_mlp.net[-1]
            A = pca.components @ comps.T  # [k', k]
            last.weight.copy_(A @ last.weight)
            last.bias.copy_(A @ last.bias + pca.components @ (mean - pca.mean))
        if self._pca is None or self._pca[0] != ipca.version:
            self.revision += 1
        self._pca = (ipca.version, pca.mean.clone(), pca.components.clone())

    def _train_view(self, kf):
        """K, size, masks [M, th*tw], scales [M], ray weights [th*tw] and held-out pixels [th*tw] of a
        keyframe at the training width (sampling.training_view), cached per keyframe and supervision."""
        sup = self.mapper.supervision.by_keyframe[kf.index]
        w, h = kf.size
        tw = min(self.cfg.train_width, w)
        th = max(1, int(round(h * tw / w)))
        K = scale_intrinsics(kf.K, tw / w, th / h)
        hit = self._masks.get(kf.index)
        if hit is None or hit[0] != sup.serial:
            hit = self._masks[kf.index] = (sup.serial, *training_view(sup, kf.index, w, h, tw, th, self.cfg))
        return K, tw, th, *hit[1:]

    # ---------------------------------------------------------------------------- training

    def train_step(self) -> dict:
        """One step on one supervised keyframe. Returns the losses, or {"skipped": reason} (a no-op)."""
        with self.lock:
            t0 = time.perf_counter()
            self.sync()
            why = self._refresh_supervision()
            if why is not None:
                return {"skipped": why}
            c = self.cfg
            kf = sample_keyframe(self._supervised(), c.window, c.revisit, self._rng)
            K, tw, th, masks, scales, weights, held = self._train_view(kf)
            weights = torch.where(held, torch.zeros(()), weights)
            targets = self.mapper.supervision.compressed(kf.index)  # [M, 64] in the current basis
            lat = self.latents.clone().requires_grad_(True)
            out = self._render(lat, K, kf.cam_to_world, tw, th, return_ids=c.lambda_consistency > 0, colour=False)
            P = min(c.rays_per_step, tw * th)
            P = min(P, int((weights > 0).sum()))
            pix = torch.multinomial(weights, P, replacement=False, generator=self._rng)
            # Scales of this step: each mask's own (L_lang of mask i at s_i; at most 16) and
            # `scales_per_step` interval samples (GARField), shared by both losses.
            own = torch.unique(scales)
            if len(own) > 16:
                own = own[torch.randperm(len(own), generator=self._rng)[:16]]
            sampled = [sample_scale(scales, self._rng) for _ in range(c.scales_per_step)]
            f, l_lang, l_in = self._view_loss(out.channels.reshape(-1, c.latent_dim), pix, masks, scales,
                                              targets, own, sampled)
            loss = c.lambda_language * l_lang + c.lambda_instance * l_in
            if c.lambda_consistency > 0 and out.ids is not None:
                # Grouping applies the mappers to each Gaussian's own latent, training to blended
                # latents: pull the dominant Gaussian of each sampled pixel to the pixel's latent.
                dom = out.ids.reshape(-1)[pix]
                hit = dom >= 0
                if bool(hit.any()):
                    l_con = ((lat[dom[hit]] - f[hit].detach()) ** 2).sum(-1).mean()
                    loss = loss + c.lambda_consistency * l_con
            self.mlp_optim.zero_grad(set_to_none=True)
            loss.backward()
            for p in list(self.language_mlp.parameters()) + list(self.instance_mlp.parameters()):
                if p.grad is not None:
                    p.grad.nan_to_num_(0.0, 0.0, 0.0)
            self.mlp_optim.step()
            # Adam on the latent rows with a gradient only: Gaussians the step did not see stay unchanged.
            seen = sparse_adam_step(self.latents, self._m, self._v, self._t, lat.grad, c.lr_latents)
            self.steps += 1
            self.revision += 1
            dt = time.perf_counter() - t0
            self.seconds += dt
            return {"loss": float(loss.detach()), "language": float(l_lang.detach()), "instance": float(l_in.detach()), "keyframe": kf.index,
                    "gaussians_updated": seen, "seconds": dt}

    def _view_loss(self, latent_img, pix, masks, scales, targets, own, sampled):
        """Pixels pix [P] of one view's latents [h*w, D] -> (f [P, D], L_lang at the `own` and `sampled`
        scales, L_in at the `sampled` scales): the training step's losses, also the stop test's."""
        c = self.cfg
        f = latent_img[pix]  # [P, D]
        members = masks[:, pix].T  # [P, M]
        lang_s = torch.cat([own.double(), torch.tensor(sampled, dtype=torch.float64)])
        tgt = torch.cat([language_targets(members, scales, targets, float(s)) for s in lang_s])  # [S P, 64]
        u = self.scale_tf(lang_s).repeat_interleave(len(pix))  # [S P]
        l_lang = language_loss(self.language_mlp(f.repeat(len(lang_s), 1), u), tgt, c.huber_delta)
        l_in = f.sum() * 0.0
        for s in sampled:
            feat = self.instance_mlp(f, self.scale_tf(s))
            l_in = l_in + instance_loss(feat, shares_group(members, scales, s), c.margin) / max(len(sampled), 1)
        return f, l_lang, l_in

    def train(self, seconds: float | None = None, iters: int | None = None, progress: bool = False,
              converge: bool | None = None, final: bool = True, until: Callable[[], bool] | None = None) -> dict:
        """Train until `seconds` or `iters` runs out or, with the stop test on, the held-out accuracy
        converged; `until()` interrupts between steps (converge.train_until says how budgets, the
        stop test and `final` combine). Returns steps, seconds, mean losses, the budget and the stop."""
        return train_until(self, seconds, iters, progress, converge, final, until)

    # ---------------------------------------------------------------------------- queries

    def _render(self, latents: torch.Tensor, K, c2w, w: int, h: int, return_ids: bool = False, colour: bool = True):
        """Channels [h, w, 3 + D]: colour and latent in one call; the latent [h, w, D] alone without `colour`.
        Only the Gaussians that can touch the image are gathered (render.frustum_cull): the same image
        and ids, without copying a room-sized map's latents for one camera."""
        g = self.mapper.gaussians
        cam = self.mapper.camera(K, c2w, w, h)
        means, scales, opac = g.means.detach(), g.scales.detach(), g.opacities.detach()
        idx = frustum_cull(means, scales, opac, cam)                               # [M]
        culled = len(idx) < len(means)
        sub = (lambda t: t[idx]) if culled else (lambda t: t)
        ch = torch.cat([sub(g.colors.detach()), sub(latents)], 1) if colour else sub(latents)
        out = rasterize(sub(means), sub(scales), sub(g.quats.detach()), sub(opac), ch, cam, return_ids=return_ids,
                        antialiased=self.mapper.cfg.antialiased)
        if culled and return_ids and out.ids is not None:
            out.ids = torch.where(out.ids >= 0, idx[out.ids.clamp(min=0)], out.ids)
        return out

    @torch.no_grad()
    def render(self, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int) -> FieldRender:
        """Colour, depth, alpha and latent [h, w, D] of the map from a camera (K at width x height)."""
        with self.lock:
            self.sync()
            out = self._render(self.latents, K, cam_to_world, width, height)
        return FieldRender(out.channels[..., 3:], out.channels[..., :3], out.depth, out.alpha)

    def normalise_scale(self, s) -> torch.Tensor:
        """Physical scale (m; float or tensor) -> [0, 1] through the fitted quantile transform."""
        if self.scale_tf is None:
            with self.lock:
                if self._refresh_supervision() is not None or self.scale_tf is None:
                    raise RuntimeError("field: no scale transform yet (no supervision masks with scales)")
        return self.scale_tf(s)

    @torch.no_grad()
    def language(self, latent: torch.Tensor, scale) -> torch.Tensor:
        """latent [..., D], scale (m, float or [...]) -> [..., language_dim] in the PCA space."""
        return self.language_mlp(latent.float(), self.normalise_scale(scale))

    @torch.no_grad()
    def instance(self, latent: torch.Tensor, scale) -> torch.Tensor:
        """latent [..., D], scale (m) -> [..., instance_dim], unit rows."""
        return self.instance_mlp(latent.float(), self.normalise_scale(scale))

    @torch.no_grad()
    def gaussian_instance(self, scale, idx: torch.Tensor | None = None) -> torch.Tensor:
        """Instance feature of every Gaussian (or of those `idx` [M]) at one scale: [N or M,
        instance_dim] (for grouping)."""
        with self.lock:
            self.sync()
            return self.instance(self.latents if idx is None else self.latents[idx], scale)

    # ---------------------------------------------------------------------------- persistence

    def state_dict(self) -> dict:
        from ..config import config_to_dict

        with self.lock:
            return {"config": config_to_dict(self.cfg), "latents": self.latents.clone(),
                    "language_mlp": {k: v.clone() for k, v in self.language_mlp.state_dict().items()},
                    "instance_mlp": {k: v.clone() for k, v in self.instance_mlp.state_dict().items()},
                    "scale": self.scale_tf.state_dict() if self.scale_tf is not None else None,
                    "pca_version": int(self._pca[0]) if self._pca is not None else -1,
                    "steps": self.steps, "seconds": float(self.seconds), "stop": self.stop}

    @staticmethod
    def from_state_dict(mapper, d: dict) -> FeatureField:
        """Rebuild a field on a loaded map (raises ValueError naming the mismatch)."""
        from ..config import config_from_dict

        f = FeatureField(mapper, config_from_dict(d["config"], FieldConfig))
        lat = d["latents"].float()
        if tuple(lat.shape) != (len(mapper.gaussians), f.cfg.latent_dim):
            raise ValueError(f"field latents are {list(lat.shape)}, map has {len(mapper.gaussians)} Gaussians "
                             f"of latent_dim {f.cfg.latent_dim}")
        f.latents = lat.clone()
        f.language_mlp.load_state_dict(d["language_mlp"])
        f.instance_mlp.load_state_dict(d["instance_mlp"])
        f.scale_tf = QuantileScale.from_state_dict(d["scale"]) if d.get("scale") is not None else None
        sset = getattr(mapper, "supervision", None)
        if sset is not None and sset.pca.pca is not None and int(d.get("pca_version", -1)) == sset.pca.version:
            p = sset.pca.pca
            f._pca = (sset.pca.version, p.mean.clone(), p.components.clone())
        f.steps, f.seconds, f.stop = int(d.get("steps", 0)), float(d.get("seconds", 0.0)), d.get("stop")
        if f.stop is None and f.steps:  # saved before the stop test existed
            f.stop = {"stopped": "unrecorded", "steps": f.steps, "seconds": round(f.seconds, 3)}
        return f
