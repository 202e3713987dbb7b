"""Gaussian map parameters and an Adam optimiser whose state follows additions and pruning.

Parameters are stored unconstrained (log scales, opacity logits) and activated on use, so the
optimiser can never produce a negative scale or an opacity outside [0, 1].
"""
from __future__ import annotations

import math

import torch

from ..render.projection import quat_to_rotmat

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "colors")  # one row per Gaussian
GLOBALS = ("background",)  # shared by the whole map


class GaussianModel:
    """N Gaussians: means [N, 3], log_scales [N, 3], quats [N, 4], opacity_logits [N], colors [N, 3],
    and uids [N] int64: lineage ids, new for each appended Gaussian and passed on to its split
    children and clones (what a taught object keeps of its group: the survivors of refinement,
    pruning and eviction are still recognised). Not optimised, not in `tensors()`."""

    def __init__(self):
        self.means = torch.zeros(0, 3)
        self.log_scales = torch.zeros(0, 3)
        self.quats = torch.zeros(0, 4)
        self.opacity_logits = torch.zeros(0)
        self.colors = torch.zeros(0, 3)
        # Colour seen where no Gaussian is (sky, beyond the depth range): learnt from those pixels.
        self.background = torch.zeros(3)
        self.uids = torch.zeros(0, dtype=torch.long)
        self._next_uid = [0]   # shared with shallow copies (snapshots): no id is given twice

    @property
    def next_uid(self) -> int:
        return self._next_uid[0]

    @next_uid.setter
    def next_uid(self, value: int) -> None:
        self._next_uid[0] = int(value)

    def __len__(self) -> int:
        return self.means.shape[0]

    def tensors(self) -> dict[str, torch.Tensor]:
        """Per-Gaussian tensors and the map's global ones (what the optimiser updates)."""
        return {k: getattr(self, k) for k in PARAMS + GLOBALS}

    @property
    def scales(self) -> torch.Tensor:  # [N, 3]
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:  # [N]
        return torch.sigmoid(self.opacity_logits)

    def append(self, means, scales, colors, opacity: float) -> None:
        """Add Gaussians: means [M, 3], isotropic or per-axis scales [M] / [M, 3], colors [M, 3]."""
        m = means.shape[0]
        scales = scales[:, None].expand(m, 3) if scales.ndim == 1 else scales
        q = torch.zeros(m, 4)
        q[:, 0] = 1.0
        o = min(max(opacity, 1e-4), 1 - 1e-4)
        new = {"means": means.float(), "log_scales": torch.log(scales.float()), "quats": q,
               "opacity_logits": torch.full((m,), math.log(o / (1 - o))), "colors": colors.float()}
        for k, v in new.items():
            setattr(self, k, torch.cat([getattr(self, k).detach(), v]))
        self.uids = torch.cat([self.uids, torch.arange(self.next_uid, self.next_uid + m, dtype=torch.long)])
        self.next_uid += m

    def split(self, idx: torch.Tensor, generator: torch.Generator | None = None, factor: float = 1.6) -> None:
        """Replace the Gaussians idx [M] by two each, drawn from the parent's own distribution, with
        scales / factor (3D Gaussian Splatting's split); the children go to the end, the parents away."""
        if not len(idx):
            return
        idx = torch.as_tensor(idx, dtype=torch.long)
        R = quat_to_rotmat(self.quats[idx])                                          # [M, 3, 3]
        s = self.scales[idx]                                                         # [M, 3]
        eps = torch.randn((2,) + tuple(s.shape), generator=generator)                # [2, M, 3]
        means = (self.means[idx][None] + torch.einsum("mij,kmj->kmi", R, eps * s[None])).reshape(-1, 3)
        new = {"means": means, "log_scales": (self.log_scales[idx] - math.log(factor)).repeat(2, 1),
               "quats": self.quats[idx].repeat(2, 1), "opacity_logits": self.opacity_logits[idx].repeat(2),
               "colors": self.colors[idx].repeat(2, 1)}
        keep = torch.ones(len(self), dtype=torch.bool)
        keep[idx] = False
        for k in PARAMS:
            setattr(self, k, torch.cat([getattr(self, k).detach()[keep], new[k].detach()]))
        self.uids = torch.cat([self.uids[keep], self.uids[idx].repeat(2)])

    def duplicate(self, idx: torch.Tensor) -> None:
        """Append a copy of the Gaussians idx [M] (3D Gaussian Splatting's clone: the copy then
        moves along its own gradient)."""
        idx = torch.as_tensor(idx, dtype=torch.long)
        for k in PARAMS:
            t = getattr(self, k).detach()
            setattr(self, k, torch.cat([t, t[idx]]))
        self.uids = torch.cat([self.uids, self.uids[idx]])

    def keep(self, mask: torch.Tensor) -> None:
        """Keep only Gaussians where mask [N] is True."""
        for k in PARAMS:
            setattr(self, k, getattr(self, k).detach()[mask])
        self.uids = self.uids[mask]

    def isolate(self, ids: torch.Tensor) -> dict[int, int]:
        """Give the Gaussians ids [M] lineage ids no Gaussian outside them carries: each of their
        uids that others share (siblings of a split or clone) is replaced, for them, by a new one.
        -> {old uid: new uid} of what changed (the uids of `ids` then name exactly them and their
        later descendants)."""
        ids = torch.as_tensor(ids, dtype=torch.long)
        inside = torch.zeros(len(self), dtype=torch.bool)
        inside[ids] = True
        shared = torch.unique(self.uids[inside])
        shared = shared[torch.isin(shared, self.uids[~inside])]
        if not len(shared):
            return {}
        new = torch.arange(self.next_uid, self.next_uid + len(shared), dtype=torch.long)
        self.next_uid += len(shared)
        hit = inside & torch.isin(self.uids, shared)
        uids = self.uids.clone()
        uids[hit] = new[torch.searchsorted(shared, self.uids[hit])]
        self.uids = uids
        return dict(zip(shared.tolist(), new.tolist()))

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {**{k: v.detach().clone() for k, v in self.tensors().items()}, "uids": self.uids.clone(),
                "next_uid": torch.tensor(self.next_uid, dtype=torch.long)}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        n = state["means"].shape[0]
        for k in PARAMS + GLOBALS:
            if k not in state:
                raise ValueError(f"map file: gaussians.{k} is missing")
            t = state[k]
            expect = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,), "colors": (n, 3),
                      "background": (3,)}[k]
            if tuple(t.shape) != expect:
                raise ValueError(f"map file: gaussians.{k} has shape {list(t.shape)}, expected {list(expect)}")
            setattr(self, k, t.float().clone())
        uids = state.get("uids")   # maps saved before lineage ids: new ones
        if uids is not None and tuple(uids.shape) != (n,):
            raise ValueError(f"map file: gaussians.uids has shape {list(uids.shape)}, expected [{n}]")
        self.uids = uids.long().clone() if uids is not None else torch.arange(n, dtype=torch.long)
        self.next_uid = max(int(state.get("next_uid", torch.tensor(0))), int(self.uids.max()) + 1 if n else 0)


class ResizableAdam:
    """Adam over the model's tensors; moments are extended with zeros for new Gaussians and indexed
    on pruning, so optimisation continues smoothly while the map changes size."""

    def __init__(self, model: GaussianModel, lrs: dict[str, float], betas=(0.9, 0.999), eps: float = 1e-15):
        self.model, self.lrs, self.betas, self.eps = model, lrs, betas, eps
        self.m = {k: torch.zeros_like(v) for k, v in model.tensors().items()}
        self.v = {k: torch.zeros_like(v) for k, v in model.tensors().items()}
        self.t = 0

    def sync(self) -> None:
        """Grow the moments to the model's current size (new Gaussians start with zero moments)."""
        for k, p in self.model.tensors().items():
            if k in GLOBALS:
                continue
            extra = p.shape[0] - self.m[k].shape[0]
            if extra > 0:
                z = torch.zeros((extra,) + tuple(p.shape[1:]))
                self.m[k], self.v[k] = torch.cat([self.m[k], z]), torch.cat([self.v[k], z])

    def keep(self, mask: torch.Tensor) -> None:
        for k in PARAMS:
            self.m[k], self.v[k] = self.m[k][mask], self.v[k][mask]

    @torch.no_grad()
    def step(self, grads: dict[str, torch.Tensor]) -> None:
        self.t += 1
        b1, b2 = self.betas
        c1, c2 = 1 - b1 ** self.t, 1 - b2 ** self.t
        for k, g in grads.items():
            if g is None or self.lrs.get(k, 0.0) == 0.0:
                continue
            g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)  # a bad pixel never poisons the map
            self.m[k].mul_(b1).add_(g, alpha=1 - b1)
            self.v[k].mul_(b2).addcmul_(g, g, value=1 - b2)
            upd = (self.m[k] / c1) / ((self.v[k] / c2).sqrt() + self.eps)
            p = getattr(self.model, k)
            setattr(self.model, k, (p - self.lrs[k] * upd).detach())
