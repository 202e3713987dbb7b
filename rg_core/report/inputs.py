"""Inputs the report builds: degraded frames (sensor noise, holes, pose error), maps resized to a
given number of Gaussians (query latency against map size), and a Mapper that seeds everywhere."""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..map.mapper import Mapper


class DegradedFrame:
    """A Frame whose depth and/or pose are corrupted reproducibly (seeded by the frame index);
    masks and RGB stay clean (oracle supervision measures what geometry errors cost)."""

    def __init__(self, frame, depth_sigma: float = 0.0, missing: float = 0.0, pose_t: float = 0.0,
                 pose_deg: float = 0.0, seed: int = 0):
        self._f, self.depth_sigma, self.missing = frame, depth_sigma, missing
        rng = np.random.default_rng(seed * 100003 + frame.index)
        self._seed = int(rng.integers(1 << 31))
        c2w = np.array(frame.cam_to_world, np.float64)
        if pose_t > 0 or pose_deg > 0:
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            a = np.deg2rad(pose_deg)
            Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            R = np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx  # Rodrigues: a rotation of pose_deg
            d = rng.normal(size=3)
            c2w[:3, :3] = R @ c2w[:3, :3]
            c2w[:3, 3] += pose_t * d / np.linalg.norm(d)
        self.cam_to_world = c2w  # [4, 4] OpenCV axes

    def __getattr__(self, name):  # index, intrinsics, stamp, load_rgb, load_visible_mask, ...
        return getattr(self._f, name)

    def load_depth(self) -> np.ndarray:  # [H, W] float32 metres, 0 = invalid
        d = self._f.load_depth().copy()
        rng = np.random.default_rng(self._seed)
        valid = d > 0
        if self.depth_sigma > 0:
            d[valid] += rng.normal(0.0, self.depth_sigma, int(valid.sum())).astype(np.float32)
            d[valid & (d <= 0)] = 0.0
        if self.missing > 0:
            d[rng.random(d.shape) < self.missing] = 0.0
        return d


DEGRADATIONS = {
    "depth_noise_1cm": dict(depth_sigma=0.01),
    "depth_noise_5cm": dict(depth_sigma=0.05),
    "missing_depth_20": dict(missing=0.2),
    "pose_noise_1cm_1deg": dict(pose_t=0.01, pose_deg=1.0),
}


def degrade(frames: list, kind: str, seed: int = 0) -> list:
    if kind not in DEGRADATIONS:
        raise ValueError(f"unknown degradation {kind!r}; known: {sorted(DEGRADATIONS)}")
    return [DegradedFrame(f, seed=seed, **DEGRADATIONS[kind]) for f in frames]


class SeedEverywhereMapper(Mapper):
    """The saving 'seed only unexplained pixels' turned off: a keyframe seeds at every valid depth
    pixel (one per stride block), as a mapper without the explained-pixel test would."""

    def _seed(self, fr, unexplained: torch.Tensor, depth=None, stride=None):
        if depth is None:  # the unexplained-pixel seeding (densification seeds stay as they are)
            unexplained = torch.from_numpy(fr.depth) > 0
        return super()._seed(fr, unexplained, depth, stride)


@torch.no_grad()
def resized_map(mapper: Mapper, field, n: int, seed: int = 0, tile: bool = False):
    """A copy of (mapper, field) with exactly n Gaussians: a random subset when n is smaller, else
    every Gaussian plus copies of random ones jittered by half their scale (latent copied too).
    tile: the copies are whole copies of the map instead, side by side on a square grid in the map's
    x-y plane, 1.5 x its extent apart (the last one partial): a larger area at the same density,
    what a robot's room-scale map is, with the keyframes of the first copy only."""
    from ..field import FeatureField

    if n < 1:
        raise ValueError(f"map size must be >= 1 Gaussian, got {n}")
    g = mapper.gaussians
    N = len(g)
    rng = torch.Generator().manual_seed(seed)
    if n <= N:
        idx = torch.randperm(N, generator=rng)[:n].sort().values                 # [n]
        jitter = torch.zeros(n, 3)
    elif tile:
        copies = -(-n // N)
        side = int(np.ceil(np.sqrt(copies)))
        means = g.means.detach()
        step = 1.5 * float((means.max(0).values - means.min(0).values)[:2].max().clamp(min=0.1))
        idx = torch.arange(n) % N                                                # [n]
        k = torch.arange(n) // N                                                 # copy of each row
        jitter = torch.stack([(k % side).float() * step, (k // side).float() * step, torch.zeros(n)], 1)
    else:
        extra = torch.randint(0, N, (n - N,), generator=rng)
        idx = torch.cat([torch.arange(N), extra])                                # [n]
        jitter = torch.cat([torch.zeros(N, 3), torch.randn(n - N, 3, generator=rng) * 0.5 * g.scales[extra]])
    m = Mapper(mapper.cfg)
    for k in ("log_scales", "quats", "opacity_logits", "colors"):
        setattr(m.gaussians, k, getattr(g, k).detach()[idx].clone())
    m.gaussians.means = g.means.detach()[idx] + jitter                           # [n, 3]
    m.gaussians.uids, m.gaussians.next_uid = g.uids[idx].clone(), g.next_uid
    m.gaussians.background = g.background.detach().clone()
    m.keyframes, m.supervision = mapper.keyframes, mapper.supervision
    m.totals = dict(mapper.totals)
    d = field.state_dict()
    d["latents"] = d["latents"][idx]                                            # [n, D]
    return m, FeatureField.from_state_dict(m, d)


def with_section(cfg, section: str, **over):
    """RGConfig copy with fields of one section (map, field, ground, ...) replaced."""
    return dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **over)})
