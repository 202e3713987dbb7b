"""Oracle supervision from a synthetic scene's ground truth, and the two checks it makes possible.

Oracle masks are the ground-truth visible instance masks (each object's at its object scale,
plus optionally one group mask: the union of the visible objects); each mask's feature is the
embedding of the object's name. With perfect supervision, any error left is the field's own:
    - relevancy: argmax of cos(decompressed language feature, name embedding) lies in the object,
    - separation: at the object's scale, its pixels' instance features are closest to its own mean.
"""
from __future__ import annotations

import zlib
from collections.abc import Callable

import numpy as np
import torch

from ..geometry.conventions import scale_intrinsics
from ..perception.supervision import KeyframeSupervision, SupervisionSet

GROUP_NAME = "objects on the table"


class RandomNameEmbedding:
    """Fixed random unit vectors per name (tests without a text model): names -> [n, dim]."""

    def __init__(self, dim: int = 96, seed: int = 0):
        self.dim, self.seed = dim, seed

    def __call__(self, names: list[str]) -> torch.Tensor:
        rows = []
        for n in names:
            g = torch.Generator().manual_seed(self.seed * 1000003 + zlib.crc32(n.encode()))
            rows.append(torch.nn.functional.normalize(torch.randn(self.dim, generator=g), dim=0))
        return torch.stack(rows) if rows else torch.zeros(0, self.dim)


def object_scale(aabb_min, aabb_max) -> float:
    """Std dev (sqrt of the covariance trace) of points uniform in the box: a view-independent scale (m)."""
    ext = np.asarray(aabb_max, np.float64) - np.asarray(aabb_min, np.float64)
    return float(np.sqrt((ext ** 2).sum() / 12.0))


def working_ids(frame, width: int):
    """A frame's ground-truth instance ids at the mapper's working width (nearest resampling, as the
    mapper resizes: aspect kept). Returns K [3, 3], cam_to_world [4, 4], w, h, ids [h, w] uint8."""
    ids = frame.load_visible_mask()
    H, W = ids.shape
    w = min(width, W)
    h = max(1, int(round(H * w / W)))
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    return scale_intrinsics(frame.intrinsics.K, w / W, h / H), frame.cam_to_world, w, h, ids[rows][:, cols]


def oracle_supervision(mapper, frames: list, objects: list, embed: Callable[[list[str]], torch.Tensor],
                       group: bool = True, min_pixels: int = 1, pca_dim: int = 64) -> SupervisionSet:
    """Supervision for every keyframe of `mapper` from ground truth; `frames` is the list that was
    streamed into the mapper (keyframe.index is a position in it). Sets and returns mapper.supervision."""
    by_id = {o.id: o for o in objects}
    if not by_id:
        raise ValueError("oracle_supervision: the scene lists no objects")
    names = sorted({o.name for o in objects})
    emb = dict(zip(names, embed(names).float()))
    group_emb = embed([GROUP_NAME]).float()[0]
    lo = np.min([o.aabb_min for o in objects], 0)
    hi = np.max([o.aabb_max for o in objects], 0)
    group_scale = object_scale(lo, hi)
    sset = SupervisionSet(pca_dim, source="oracle")
    for kf in mapper.keyframes:
        if kf.index >= len(frames):
            raise ValueError(f"oracle_supervision: keyframe {kf.index} is beyond the {len(frames)} frames given")
        w, h = kf.size
        _, _, _, _, ids = working_ids(frames[kf.index], w)
        if ids.shape != (h, w):
            raise ValueError(f"oracle_supervision: frame {kf.index} resamples to {ids.shape}, keyframe is {(h, w)}")
        masks, scales, levels, rows = [], [], [], []
        for oid in sorted(int(i) for i in np.unique(ids) if i != 0 and int(i) in by_id):
            m = ids == oid
            if m.sum() < min_pixels:
                continue
            o = by_id[oid]
            masks.append(m), scales.append(object_scale(o.aabb_min, o.aabb_max)), levels.append(1)
            rows.append(emb[o.name])
        if group and len(masks) > 1:
            masks.append(np.any(masks, 0)), scales.append(group_scale), levels.append(2), rows.append(group_emb)
        M = len(masks)
        sup = KeyframeSupervision(
            masks=np.stack(masks) if M else np.zeros((0, h, w), bool), scores=np.ones(M, np.float32),
            levels=np.array(levels, np.int8), scales=np.array(scales, np.float32),
            embeddings=torch.stack(rows) if M else torch.zeros(0, group_emb.shape[0]))
        sset.add(kf.index, sup)
    mapper.supervision = sset
    return sset


@torch.no_grad()
def oracle_checks(field, frames: list, objects: list, embed: Callable[[list[str]], torch.Tensor],
                  n_scales: int = 9, min_pixels: int = 20, min_alpha: float = 0.5, smooth: int = 3) -> dict:
    """The two checks on (held-out) frames. Relevancy takes, per pixel, the best cosine over
    `n_scales` scales evenly spaced in the field's scale quantiles (grounding searches scales too);
    argmax and means use pixels the map covers (alpha > min_alpha). `argmax_in_mask` takes the
    argmax of the relevancy box-filtered over smooth x smooth pixels (a robust peak: features bleed
    a Gaussian's footprint, 1-4 px, over object borders); `argmax_in_mask_raw` the unfiltered one.
    Objects with fewer than `min_pixels` covered pixels in a view are not counted."""
    sset = field.mapper.supervision
    pca = sset.pca.pca
    by_id = {o.id: o for o in objects}
    names = sorted({o.name for o in objects})
    E = torch.nn.functional.normalize(embed(names).float(), dim=-1)  # [O, D]
    col = {n: i for i, n in enumerate(names)}
    knots = field.scale_tf.knots
    grid = torch.exp(knots[torch.linspace(0, len(knots) - 1, n_scales).round().long()]).float()
    hits = raw_hits = pairs = close = total = 0
    per_view = []
    for fr in frames:
        K, c2w, w, h, ids = working_ids(fr, field.mapper.cfg.width)
        r = field.render(K, c2w, w, h)
        ids_t = torch.from_numpy(ids.astype(np.int64))
        cov = r.alpha > min_alpha
        present = [int(i) for i in np.unique(ids) if i != 0 and int(i) in by_id
                   and int(((ids_t == int(i)) & cov).sum()) >= min_pixels]
        rel = torch.full((h, w, len(names)), -2.0)
        for s in grid:
            x = torch.nn.functional.normalize(pca.inverse(field.language(r.latent, float(s))), dim=-1)
            rel = torch.maximum(rel, x @ E.T)
        rel = torch.where(cov[..., None], rel, torch.full_like(rel, -3.0))  # [h, w, O]
        sm = torch.nn.functional.avg_pool2d(rel.permute(2, 0, 1)[None], smooth, 1, smooth // 2,
                                            count_include_pad=False)[0].permute(1, 2, 0) if smooth > 1 else rel
        v_hits = 0
        for oid in present:
            j = col[by_id[oid].name]
            v_hits += int(ids_t.reshape(-1)[int(sm[..., j].reshape(-1).argmax())] == oid)
            raw_hits += int(ids_t.reshape(-1)[int(rel[..., j].reshape(-1).argmax())] == oid)
            s_o = object_scale(by_id[oid].aabb_min, by_id[oid].aabb_max)
            feat = field.instance(r.latent, s_o)  # [h, w, Di]
            means = torch.stack([feat[(ids_t == j) & cov].mean(0) for j in present])  # [V, Di]
            own = feat[(ids_t == oid) & cov]  # [p, Di]
            nearest = torch.cdist(own, means).argmin(1)
            close += int((nearest == present.index(oid)).sum())
            total += len(own)
        hits += v_hits
        pairs += len(present)
        per_view.append({"frame": fr.index, "objects": len(present), "argmax_hits": v_hits})
    return {"argmax_in_mask": hits / max(pairs, 1), "argmax_in_mask_raw": raw_hits / max(pairs, 1), "pairs": pairs,
            "instance_separation": close / max(total, 1), "pixels": total, "views": per_view}
