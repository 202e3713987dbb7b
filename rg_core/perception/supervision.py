"""Per-keyframe 2D supervision, computed once and stored with the map: masks -> physical scales ->
image-text embeddings, plus the map-wide PCA that compresses embeddings to the field's 64 dims."""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .embed import Embedder, mask_crop
from .masks import MaskGenerator
from .pca import IncrementalPCA
from .scale import MaskScaleError, mask_scale

_SERIALS = itertools.count(1)


def _renewed(obj):
    """copy.copy of `obj` under a serial of its own: caches keyed by serial see a copy as new."""
    c = object.__new__(type(obj))
    c.__dict__.update(obj.__dict__)
    c.serial = next(_SERIALS)
    return c


@dataclass
class KeyframeSupervision:
    masks: np.ndarray          # [M, h, w] bool, at the keyframe's working resolution
    scores: np.ndarray         # [M] float32 confidence
    levels: np.ndarray         # [M] int8: 0 part, 1 object, 2 group
    scales: np.ndarray         # [M] float32 physical scale (m)
    embeddings: torch.Tensor   # [M, D] raw image-text embeddings (unit rows)
    seconds: dict = field(default_factory=dict)  # per stage: masks, scales, embed
    dropped: int = 0           # masks without a measurable scale or crop
    embeddings_view: torch.Tensor | None = None  # [M, D] per-view embeddings once `embeddings` hold
                                                 # multi-view means (perception.multiview)
    own: np.ndarray | None = None  # [M] bool: masks with their own embedding (None: all); the others
                                   # take their object's multi-view mean (supervise_map_multiview)

    # What people taught (grounding/teach.py): per mask the taught name ("" = the model's label),
    # the model's own embeddings to restore, and which masks teaching added. None: nothing taught.
    taught: np.ndarray | None = None   # [M] object (str)
    model: torch.Tensor | None = None  # [M, D]
    added: np.ndarray | None = None    # [M] bool
    # What caches key this record by (field training views, held-out probes, query scopes): unique for
    # the process, new for every record, copy and dataclasses.replace; id() is reused once freed.
    serial: int = field(default_factory=lambda: next(_SERIALS), init=False, repr=False, compare=False)

    __copy__ = _renewed

    def owned(self) -> np.ndarray:  # [M] bool
        return np.ones(len(self.scales), bool) if self.own is None else self.own

    def state_dict(self) -> dict:
        M, h, w = self.masks.shape
        return {"shape": [M, h, w], "masks": torch.from_numpy(np.packbits(self.masks.reshape(M, -1), axis=1)),
                "scores": torch.from_numpy(self.scores), "levels": torch.from_numpy(self.levels.astype(np.int8)),
                "scales": torch.from_numpy(self.scales), "embeddings": self.embeddings.float(),
                "seconds": {k: float(v) for k, v in self.seconds.items()}, "dropped": int(self.dropped),
                "embeddings_view": self.embeddings_view.float() if self.embeddings_view is not None else None,
                "own": torch.from_numpy(self.own.copy()) if self.own is not None else None,
                **({"taught": [str(n) for n in self.taught], "model": self.model.float(),
                    "added": torch.from_numpy(self.added.copy())} if self.taught is not None else {})}

    @staticmethod
    def from_state_dict(d: dict) -> "KeyframeSupervision":
        M, h, w = (int(v) for v in d["shape"])
        masks = np.unpackbits(d["masks"].numpy(), axis=1, count=h * w).reshape(M, h, w).astype(bool)
        return KeyframeSupervision(masks, d["scores"].numpy(), d["levels"].numpy(), d["scales"].numpy(),
                                   d["embeddings"].float(), dict(d.get("seconds", {})), int(d.get("dropped", 0)),
                                   d["embeddings_view"].float() if d.get("embeddings_view") is not None else None,
                                   d["own"].numpy().astype(bool) if d.get("own") is not None else None,
                                   np.array(list(d["taught"]), dtype=object) if d.get("taught") is not None else None,
                                   d["model"].float() if d.get("taught") is not None else None,
                                   d["added"].numpy().astype(bool) if d.get("taught") is not None else None)


def build_supervision(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, generator: MaskGenerator,
                      embedder: Embedder, rendered_depth: np.ndarray | None = None,
                      min_points: int = 20, embed: bool = True) -> KeyframeSupervision:
    """rgb [h, w, 3] uint8, depth [h, w] m, K [3, 3]; `rendered_depth` from the map fills depth holes
    when measuring scales. Masks whose scale cannot be measured are dropped (and counted).
    embed=False: masks and scales only (zero embeddings, `own` all False; embed_masks fills them)."""
    if rgb.shape[:2] != depth.shape:
        raise ValueError(f"supervision: rgb {rgb.shape[:2]} and depth {depth.shape} differ in size")
    t0 = time.perf_counter()
    masks = generator.generate(rgb, depth, K)
    t1 = time.perf_counter()
    kept, scales = [], []
    for m in masks:
        try:
            scales.append(mask_scale(m.mask, depth, K, rendered_depth, min_points))
            mask_crop(rgb, m.mask)  # raises for masks too small to crop
            kept.append(m)
        except (MaskScaleError, ValueError):
            continue
    t2 = time.perf_counter()
    emb = embedder.encode_masks(rgb, kept) if kept and embed else torch.zeros(len(kept), embedder.dim)
    t3 = time.perf_counter()
    h, w = depth.shape
    return KeyframeSupervision(
        masks=np.stack([m.mask for m in kept]) if kept else np.zeros((0, h, w), bool),
        scores=np.array([m.score for m in kept], np.float32), levels=np.array([m.level for m in kept], np.int8),
        scales=np.array(scales, np.float32), embeddings=emb,
        seconds={"masks": t1 - t0, "scales": t2 - t1, "embed": t3 - t2}, dropped=len(masks) - len(kept),
        own=None if embed else np.zeros(len(kept), bool))


def embed_masks(sup: KeyframeSupervision, rgb: np.ndarray, embedder: Embedder, which: np.ndarray) -> int:
    """Embed the masks `which` [M] bool of a keyframe (rgb [h, w, 3] uint8) that lack their own
    embedding; returns how many were embedded."""
    from .masks import Mask

    todo = np.flatnonzero(which & ~sup.owned())
    if len(todo):
        t = time.perf_counter()
        emb = embedder.encode_masks(rgb, [Mask(sup.masks[i], float(sup.scores[i]), int(sup.levels[i])) for i in todo])
        for e in (sup.embeddings, sup.embeddings_view):
            if e is not None:
                e[torch.from_numpy(todo)] = emb.to(e)
        own = sup.owned().copy()
        own[todo] = True
        sup.own = own
        sup.seconds["embed"] = sup.seconds.get("embed", 0.0) + time.perf_counter() - t
    return len(todo)


TEXT_MODEL = "all-MiniLM-L6-v2"  # the model of SupervisionSet.text_embeddings (rg_core.perception.minilm)


class SupervisionSet:
    """Supervision of every keyframe of a map and the PCA space of their embeddings."""

    def __init__(self, pca_dim: int = 64, source: str = "default"):
        self.by_keyframe: dict[int, KeyframeSupervision] = {}
        # where the masks and names came from: "default" (the preset's models) or "oracle" (ground
        # truth); answers on the two are calibrated apart (grounding.confidence).
        self.source = source
        self.pca = IncrementalPCA(k=pca_dim)
        # MiniLM embeddings of the texts a query on this map needs besides the query itself (names,
        # canonical phrases): stored with the map so a new process need not load the text model.
        self.text_embeddings: dict[str, torch.Tensor] = {}
        # (taught version, supervised keyframes) the taught labels were last applied for (teach.refresh)
        self.taught_state: tuple | None = None
        self.serial = next(_SERIALS)   # as KeyframeSupervision.serial

    __copy__ = _renewed

    def add(self, keyframe_index: int, sup: KeyframeSupervision) -> bool:
        """Store a keyframe's supervision; returns True when the PCA basis was refitted (callers
        then re-express stored targets with `compressed`)."""
        self.by_keyframe[keyframe_index] = sup
        return self.pca.add(sup.embeddings) if len(sup.embeddings) else False

    def remove(self, keyframe_index: int) -> bool:
        """Forget a keyframe's supervision (a dropped keyframe) and its raw rows of the PCA; the
        basis stays until the next refit. False when it had none."""
        sup = self.by_keyframe.pop(keyframe_index, None)
        if sup is None:
            return False
        if len(sup.embeddings):
            ptr = sup.embeddings.data_ptr()
            self.pca.raw = [r for r in self.pca.raw if r.data_ptr() != ptr]
        return True

    def compressed(self, keyframe_index: int) -> torch.Tensor:  # [M, k] in the current PCA basis
        if self.pca.pca is None:
            raise RuntimeError("PCA not fitted yet: too few masks so far")
        return self.pca.pca.transform(self.by_keyframe[keyframe_index].embeddings)

    def stats(self) -> dict:
        sups = list(self.by_keyframe.values())
        if not sups:
            return {"keyframes": 0}
        per = {k: float(np.mean([s.seconds.get(k, 0.0) for s in sups])) for k in ("masks", "scales", "embed")}
        out = {"keyframes": len(sups), "masks_per_keyframe": float(np.mean([len(s.scales) for s in sups])),
               "dropped_masks": int(sum(s.dropped for s in sups)),
               "seconds_per_keyframe": {k: round(v, 4) for k, v in per.items()}}
        if self.pca.pca is not None:
            r = self.pca.pca.explained_variance_ratio
            out["pca"] = {"dim": self.pca.pca.dim, "fitted_on": self.pca.pca.n_fit,
                          "explained_variance": round(float(r.sum()), 4), "refits": self.pca.version}
        return out

    def state_dict(self) -> dict:
        return {"keyframes": {str(k): s.state_dict() for k, s in self.by_keyframe.items()},
                "pca": self.pca.pca.state_dict() if self.pca.pca is not None else None, "pca_dim": self.pca.k,
                "pca_version": self.pca.version, "source": self.source,
                "taught_state": [int(self.taught_state[0]), [int(k) for k in self.taught_state[1]]]
                if self.taught_state is not None else None,
                "text_embeddings": {"model": TEXT_MODEL, "texts": list(self.text_embeddings),
                                    "embeddings": torch.stack(list(self.text_embeddings.values())).float()}
                if self.text_embeddings else None}

    @staticmethod
    def from_state_dict(d: dict) -> "SupervisionSet":
        from .pca import PCA

        s = SupervisionSet(int(d.get("pca_dim", 64)), str(d.get("source", "default")))
        for k, v in d["keyframes"].items():
            s.by_keyframe[int(k)] = KeyframeSupervision.from_state_dict(v)
            s.pca.raw.append(s.by_keyframe[int(k)].embeddings)
        if d.get("pca") is not None:
            s.pca.pca = PCA.from_state_dict(d["pca"])
            s.pca.version = int(d.get("pca_version", 1))
        ts = d.get("taught_state")
        s.taught_state = (int(ts[0]), tuple(int(k) for k in ts[1])) if ts is not None else None
        te = d.get("text_embeddings")
        if te is not None and te.get("model") == TEXT_MODEL:
            texts, emb = list(te["texts"]), te["embeddings"]
            if emb.ndim != 2 or len(texts) != len(emb):
                raise ValueError(f"text_embeddings: {len(texts)} texts but embeddings {list(emb.shape)}")
            s.text_embeddings = dict(zip(texts, emb.float()))
        return s


def supervise_map(mapper, generator: MaskGenerator, embedder: Embedder, progress: bool = False,
                  embed: bool = True, between=None) -> SupervisionSet:
    """Compute supervision for every keyframe of `mapper` that has none yet (once per keyframe);
    the map's rendered depth fills sensor depth holes when measuring scales. embed=False: masks and
    scales only (supervise_map_multiview embeds what it needs). `between()` is called before each
    keyframe (the node's worker waits there while a query runs)."""
    import sys

    from tqdm import tqdm

    if getattr(mapper, "supervision", None) is None:
        mapper.supervision = SupervisionSet()
    sset = mapper.supervision
    todo = [kf for kf in mapper.keyframes if kf.index not in sset.by_keyframe]
    for kf in tqdm(todo, desc="supervise", unit="kf", disable=not progress, file=sys.stderr):
        if between is not None:
            between()
        w, h = kf.size
        with torch.no_grad():
            rendered = mapper.render(kf.K, kf.cam_to_world, w, h).depth.numpy() if len(mapper.gaussians) else None
        rgb = (kf.rgb.numpy() * 255.0).round().clip(0, 255).astype(np.uint8)
        sup = build_supervision(rgb, kf.depth.numpy(), kf.K, generator, embedder, rendered, embed=embed)
        if embed:
            sset.add(kf.index, sup)
        else:  # zero rows must not reach the PCA: multiview refits it on the filled embeddings
            sset.by_keyframe[kf.index] = sup
    return sset


def supervise_map_multiview(mapper, generator: MaskGenerator, embedder: Embedder, progress: bool = False,
                            views_per_object: int = 0, between=None) -> tuple[SupervisionSet, dict]:
    """supervise_map, then one embedding per object across keyframes (multiview.aggregate_multiview):
    the supervision `rg eval` and the node train the field on. -> (set, association statistics).
    views_per_object > 0: masks and scales first; after associating them, an object is embedded in at
    most that many views (its largest masks; views already embedded count); its other masks take the
    object's mean, and a keyframe none of whose masks needs an embedding is not embedded at all."""
    from .multiview import aggregate_multiview, associate

    if views_per_object <= 0:
        sset = supervise_map(mapper, generator, embedder, progress=progress, between=between)
        return sset, aggregate_multiview(mapper, sset)
    sset = supervise_map(mapper, generator, embedder, progress=progress, embed=False, between=between)
    keys, labels = associate(mapper, sset)
    want: dict[int, np.ndarray] = {k: sup.owned().copy() for k, sup in sset.by_keyframe.items()}
    have = np.zeros(int(labels.max()) + 1 if len(labels) else 0, np.int64)
    for (k, m), lab in zip(keys, labels):
        have[lab] += int(want[k][m])
    area = np.array([sset.by_keyframe[k].masks[m].sum() for k, m in keys])
    for r in np.argsort(-area, kind="stable"):
        (k, m), lab = keys[r], labels[r]
        if not want[k][m] and have[lab] < views_per_object:
            want[k][m], have[lab] = True, have[lab] + 1
    kfs = {kf.index: kf for kf in mapper.keyframes}
    embedded = skipped_kf = 0
    for k, sup in sset.by_keyframe.items():
        need = want[k] & ~sup.owned()
        if not need.any():
            skipped_kf += int(sup.own is not None and not sup.own.any() and len(sup.scales) > 0)
            continue
        if between is not None:
            between()
        rgb = (kfs[k].rgb.numpy() * 255.0).round().clip(0, 255).astype(np.uint8)
        embedded += embed_masks(sup, rgb, embedder, need)
    stats = aggregate_multiview(mapper, sset, keys=(keys, labels))
    owned = sum(int(s.owned().sum()) for s in sset.by_keyframe.values())
    total = sum(len(s.scales) for s in sset.by_keyframe.values())
    return sset, {**stats, "embedded_now": embedded, "masks_embedded": owned, "masks_total": total,
                  "keyframes_not_embedded": skipped_kf}
