"""The query pipeline in the paper's order: reasoning -> reference view -> relevancy -> scale s* ->
HDBSCAN over instance features at s* -> the group under the most relevant pixel -> boxes.

`Grounder` holds no map state of its own: it reads the Mapper (keyframes, Gaussians, supervision)
and the FeatureField, so a node can keep mapping and training between queries.
"""
from __future__ import annotations

import logging
import time

import numpy as np
import torch

from ..config import RGConfig
from ..geometry.conventions import backproject, pixels_to_points
from ..geometry.points import map_spacing
from ..render import rasterize
from .boxes import connected_to, group_boxes, robust_inliers
from .cache import MapCache
from .carve import MaskView, mask_depth_offsets, mask_votes, registration_border
from .grouping import Groups, cluster_instances
from .relevancy import CANONICAL, relevancy, relevancy_pca
from .result import GroundedObject, GroundingResult
from .vocabulary import build_vocabulary, looks_like_name

log = logging.getLogger(__name__)


class _threads:
    """torch.set_num_threads(n) inside a block (n <= 0: leave it), restored after."""

    def __init__(self, n: int):
        self.n = n

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.n > 0 and self.n != self.old:
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        if torch.get_num_threads() != self.old:
            torch.set_num_threads(self.old)


def _spread(items: list, n: int) -> list:
    """Up to n items spread evenly from the first to the last, in order."""
    if not items:
        return []
    return [items[i] for i in sorted({round(float(i)) for i in np.linspace(0, len(items) - 1, min(n, len(items)))})]


class Grounder:
    """ground(query) -> GroundingResult; masks(result, camera) -> amodal and visible masks.

    `text_encoder(list[str]) -> [n, D]` must embed texts in the space of the map's mask embeddings
    (the embedder's encode_texts; the packaged MiniLM for the offline default). `scene_names` are
    names the caller knows the scene may hold (added to the reasoner's vocabulary).
    """

    def __init__(self, mapper, field, cfg: RGConfig | None = None, reasoner=None, text_encoder=None,
                 scene_names: list[str] | None = None, cache: bool = True):
        """cache=False recomputes everything that depends only on the map for every query (the
        baseline of benchmarks/bench_latency.py and of the cache tests)."""
        self.mapper, self.field, self.cfg = mapper, field, cfg or RGConfig()
        self.gcfg = self.cfg.ground
        self._reasoner, self._text = reasoner, text_encoder
        self.scene_names = list(scene_names or [])
        self._text_cache: dict[str, torch.Tensor] = {}
        # Clusters per (scale, region), field renders per keyframe, map spacing, vocabulary: valid
        # while the map and field are unchanged (rg_core/grounding/cache.py says how that is known).
        self.cache = MapCache(cache)
        self._outer_threads = 0  # torch's thread count outside ground(): what big work runs with
        sset = getattr(mapper, "supervision", None)
        if sset is not None and getattr(sset, "text_embeddings", None):
            from ..perception.minilm import remember

            remember(sset.text_embeddings)  # the map's stored name embeddings: no text model for them

    # ------------------------------------------------------------------------------ models

    @property
    def reasoner(self):
        if self._reasoner is None:
            from ..perception.reasoner import reasoner_from_config

            self._reasoner = reasoner_from_config(self.cfg.reason)
        return self._reasoner

    def encode(self, texts: list[str]) -> torch.Tensor:
        """[n] strings -> [n, D] unit rows (cached: canonical phrases and names repeat)."""
        if self._text is None:
            from ..perception.embed import MiniLMText

            self._text = MiniLMText()
        todo = [t for t in dict.fromkeys(texts) if t not in self._text_cache]
        if todo:
            for t, e in zip(todo, self._text(todo)):
                self._text_cache[t] = torch.nn.functional.normalize(e.float(), dim=-1)
        return torch.stack([self._text_cache[t] for t in texts]) if texts else torch.zeros(0, 1)

    def store_texts(self) -> int:
        """Embed the texts a query on this map needs besides the query itself (household, scene and
        configured names, their reasoner prompt form, the reasoner's background names, the canonical
        phrases) with MiniLM and keep them in the map's supervision: save_map then stores them, and
        a new process answers a query naming one of them without loading the text model. -> count."""
        from ..perception import reasoner as rmod
        from ..perception.embed import MiniLMText
        from .vocabulary import HOUSEHOLD

        sset = self.mapper.supervision
        if sset is None:
            raise ValueError("store_texts: the map has no supervision yet")
        template = getattr(rmod, "NAME_TEMPLATE", "{}")
        names = list(dict.fromkeys(list(self.scene_names) + list(self.gcfg.vocabulary) + list(HOUSEHOLD)
                                   + list(self.cfg.reason.extra_vocabulary)))
        background = getattr(rmod, "_background_names", lambda: [])()
        texts = list(dict.fromkeys(names + [template.format(n) for n in names + list(background)]
                                   + list(CANONICAL)))
        enc = self._text if isinstance(self._text, MiniLMText) else MiniLMText()
        sset.text_embeddings = dict(zip(texts, enc(texts)))
        return len(texts)

    def scene_image(self, max_views: int = 4) -> np.ndarray:
        """-> [H, W, 3] uint8 RGB: up to `max_views` keyframes spread evenly over the map's keyframes,
        tiled 2 x 2 at their working resolution (one keyframe alone when there is one): what an image
        reasoner is shown of the scene before the target, and so the reference view, is known."""
        kfs = self.mapper.keyframes
        if not kfs:
            raise ValueError("scene_image: the map has no keyframes")
        pick = _spread(kfs, max_views)
        h, w = pick[0].rgb.shape[:2]
        tiles = []
        for kf in pick:
            img = (kf.rgb.detach().float().clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()  # [h, w, 3]
            if img.shape[:2] != (h, w):  # keyframes of another working size: fit the first one's
                import cv2

                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            tiles.append(img)
        if len(tiles) == 1:
            return tiles[0]
        tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % 2)
        rows = [np.concatenate(tiles[i:i + 2], axis=1) for i in range(0, len(tiles), 2)]
        return np.ascontiguousarray(np.concatenate(rows, axis=0))

    def vocabulary(self) -> list[str]:
        self._check_cache()
        sset = self.mapper.supervision
        n_masks = sum(len(s.embeddings) for s in sset.by_keyframe.values()) if sset is not None else 0
        key = (n_masks, tuple(self.scene_names), tuple(self.gcfg.vocabulary), bool(self.gcfg.support_vocabulary))

        def make():
            emb = torch.cat([s.embeddings for s in sset.by_keyframe.values()]) if n_masks else torch.zeros(0, 1)
            return build_vocabulary(self.scene_names, self.gcfg.vocabulary, emb, self.encode,
                                    self.gcfg.support_vocabulary)
        return list(self.cache.get("vocabulary", key, make))

    def _check_cache(self) -> None:
        """Empty the map caches when the map, its supervision or the field changed since they were filled."""
        m, f = self.mapper, self.field
        g = m.gaussians
        tensors = (g.means, g.log_scales, g.quats, g.opacity_logits)
        sset = m.supervision
        counters = (len(g), m.frames_seen, len(m.keyframes), id(sset))
        if sset is not None:
            counters += (len(sset.by_keyframe), sum(len(s.embeddings) for s in sset.by_keyframe.values()),
                         getattr(sset.pca, "version", None), id(sset.pca.pca))
        if f is not None:
            if len(f.latents) != len(g):
                f.sync()  # latents follow Gaussians added or pruned since the last training step
            tensors += (f.latents,)
            counters += (id(f), f.steps, f._pca[0] if getattr(f, "_pca", None) is not None else None,
                         id(f.scale_tf))
        self.cache.check(tensors, counters)

    # ------------------------------------------------------------------------------ checks

    def _not_ready(self) -> str | None:
        m = self.mapper
        if not m.keyframes or not len(m.gaussians):
            return "the map is empty: no keyframes yet"
        if m.supervision is None or not m.supervision.by_keyframe or m.supervision.pca.pca is None:
            return "the map has no 2D supervision yet (masks and embeddings per keyframe)"
        if self.field is None or self.field.steps == 0:
            return "the feature field has not been trained yet"
        return None

    def _check_query(self, query) -> str | None:
        if not isinstance(query, str):
            return f"query must be a string, got {type(query).__name__}"
        if not query.strip():
            return "empty query: say what to find, e.g. 'coffee mug'"
        if len(query) > self.gcfg.max_query_chars:
            return f"query is {len(query)} characters long; at most {self.gcfg.max_query_chars} are accepted"
        return None

    # ------------------------------------------------------------------------------ pipeline

    def _mask_candidates(self, target: torch.Tensor) -> list[tuple]:
        """Per keyframe, its mask most similar to the target text [D]:
        [(similarity, mask pixels, keyframe, mask index, scale)]."""
        by_index = {kf.index: kf for kf in self.mapper.keyframes}
        cands = []
        for k, sup in self.mapper.supervision.by_keyframe.items():
            if k not in by_index or not len(sup.embeddings):
                continue
            sims = torch.nn.functional.normalize(sup.embeddings.float(), dim=-1) @ target
            i = int(sims.argmax())
            cands.append((float(sims[i]), int(sup.masks[i].sum()), by_index[k], i, float(sup.scales[i])))
        return cands

    def reference_view(self, target: torch.Tensor, cands: list[tuple] | None = None):
        """Keyframe whose mask embedding is most similar to the target text [D]:
        -> (keyframe, mask index, similarity, physical scale s*)."""
        cands = self._mask_candidates(target) if cands is None else cands
        if not cands:
            return None, -1, -2.0, 0.0
        # Among views about as similar as the best, the one that sees the target largest.
        top = max(c[0] for c in cands)
        s, _, kf, i, scale = max((c for c in cands if c[0] >= top - 0.02), key=lambda c: c[1])
        return kf, i, s, scale

    def carve_views(self, cands: list[tuple]) -> list[MaskView]:
        """The target's masks in up to `carve_views` keyframes: those whose best mask is about as
        similar to the target as the best one (the same object seen again), largest first."""
        n = self.gcfg.carve_views
        if n <= 0 or not cands:
            return []
        top = max(c[0] for c in cands)
        near = sorted((c for c in cands if c[0] >= max(top - 0.02, self.gcfg.min_mask_similarity)), key=lambda c: -c[1])
        out = []
        for _, _, kf, i, _ in near[:n]:
            mask = self.mapper.supervision.by_keyframe[kf.index].masks[i]
            if mask.shape == tuple(kf.depth.shape):
                out.append(MaskView(np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64),
                                    kf.depth.numpy(), mask))
        return out

    def groups(self, scale: float, region: np.ndarray | None = None) -> Groups:
        """Clusters of instance features at one scale, over the Gaussians in `region` (bool [N];
        None: all); cached until the map, the field or the region changes. Gaussians outside the
        region are left out: label -1 and a zero feature, so they never join a group."""
        self._check_cache()
        N = len(self.mapper.gaussians)
        key = (round(scale, 4), N, None if region is None else np.packbits(region).tobytes())

        def make() -> Groups:
            g = self.gcfg
            with _threads(self._outer_threads):
                feats = self.field.gaussian_instance(scale)                     # [N, Di]
            if region is None:
                out = cluster_instances(feats, g.max_cluster_points, g.min_cluster_size, g.cluster_eps,
                                        seed=g.seed, method=g.cluster_method)
            else:
                idx = np.nonzero(region)[0]
                sub = cluster_instances(feats[torch.from_numpy(idx)], g.max_cluster_points, g.min_cluster_size,
                                        g.cluster_eps, seed=g.seed, method=g.cluster_method)
                labels = np.full(N, -1, np.int64)
                labels[idx] = sub.labels
                full = torch.zeros_like(feats)
                full[torch.from_numpy(idx)] = sub.features
                out = Groups(labels, sub.centres, sub.clustered, sub.seconds, sub.radius, full)
            return out
        return self.cache.get("groups", key, make)

    def region(self, kf, mask: np.ndarray, depth: torch.Tensor, alpha: torch.Tensor, scale: float) -> np.ndarray | None:
        """Gaussians that can belong to the reference mask's object: within `region_scales` x s* of
        the 3D centroid of the mask (back-projected with the rendered depth). None: no depth there."""
        if self.gcfg.region_scales <= 0 or mask.shape != tuple(depth.shape):
            return None
        sel = torch.from_numpy(mask) & (alpha > self.gcfg.mask_alpha) & (depth > 0)
        if int(sel.sum()) < 3:
            return None
        pts = backproject(depth.numpy(), np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64))
        centre = torch.from_numpy(pts[sel.numpy()]).median(0).values.float()        # [3] world
        d = (self.mapper.gaussians.means.detach() - centre).norm(dim=-1)
        return (d <= self.gcfg.region_scales * max(scale, 1e-3)).numpy()

    def spacing(self) -> float:
        """The map's median nearest-neighbour distance between Gaussians (m), cached until the map
        changes (idle refinement moves Gaussians too: see rg_core/grounding/cache.py)."""
        self._check_cache()
        return self.cache.get("spacing", self.gcfg.seed,
                              lambda: map_spacing(self.mapper.gaussians.means.detach().numpy(), seed=self.gcfg.seed))

    def vote_border(self) -> int:
        """Mask growth (px) for the votes: ground.vote_border_px, or with -1 the colour/depth
        registration offset measured on up to 6 keyframes spread over the map (their supervision
        masks against their depth), cached until the map changes."""
        if self.gcfg.vote_border_px >= 0:
            return int(self.gcfg.vote_border_px)
        self._check_cache()

        def make() -> int:
            sup = self.mapper.supervision
            kfs = [kf for kf in self.mapper.keyframes if sup is not None and kf.index in sup.by_keyframe]
            if not kfs:
                return 0
            pick = _spread(kfs, 6)
            offs = []
            for kf in pick:
                depth = kf.depth.numpy()
                masks = [m for m in sup.by_keyframe[kf.index].masks
                         if m.shape == depth.shape and 50 <= int(m.sum()) <= 0.5 * m.size]
                if masks:
                    offs.append(mask_depth_offsets(depth, masks))
            return registration_border(np.concatenate(offs) if offs else np.zeros(0))

        return self.cache.get("border", self.gcfg.seed, make)

    def render_keyframe(self, kf):
        """The field rendered from a keyframe (latent, colour, depth, alpha), cached per keyframe."""
        self._check_cache()
        w, h = kf.size
        def make():
            with _threads(self._outer_threads):
                return self.field.render(kf.K, kf.cam_to_world, w, h)
        return self.cache.get("renders", (kf.index, w, h), make)

    def _decompress(self, z: torch.Tensor) -> torch.Tensor:  # [..., k] -> [..., D]
        return self.mapper.supervision.pca.pca.inverse(z)

    def ground(self, query: str, mode: str = "auto", max_results: int = 1) -> GroundingResult:
        self._outer_threads = torch.get_num_threads()
        with _threads(self.gcfg.query_threads):
            return self._ground(query, mode, max_results)

    def _ground(self, query: str, mode: str, max_results: int) -> GroundingResult:
        t = {}
        t0 = time.perf_counter()
        bad = self._check_query(query)
        if bad:
            return GroundingResult(False, bad, query=str(query)[:200])
        if mode not in ("auto", "explicit", "implicit"):
            return GroundingResult(False, f"mode must be auto, explicit or implicit, got {mode!r}", query=query)
        if max_results < 1:
            return GroundingResult(False, f"max_results must be >= 1, got {max_results}", query=query)
        not_ready = self._not_ready()
        if not_ready:
            return GroundingResult(False, not_ready, query=query)
        self._check_cache()

        vocab = self.vocabulary()
        if mode != "implicit" and looks_like_name(query) and query.strip() not in vocab:
            vocab.append(query.strip())
        # An LVLM sees the scene (the paper's reference view: the target is not known yet, so a few
        # keyframes spread over the map); text reasoners and explicit queries need no picture.
        image = self.scene_image() if mode != "explicit" and getattr(self.reasoner, "accepts_images", False) else None
        r = self.reasoner.reason(query, vocab, image=image, mode=mode)
        t["reason"] = time.perf_counter() - t0
        res = GroundingResult(False, "", query=query, target=r.target, explanation=r.explanation)
        if not r.target:
            res.message = f"nothing in the map matches {query!r}: {r.explanation}"
            res.timings = t
            return res

        t1 = time.perf_counter()
        target = self.encode([r.target])[0]
        cands = self._mask_candidates(target)
        kf, mi, msim, scale = self.reference_view(target, cands)
        t["reference_view"] = time.perf_counter() - t1
        if kf is None or msim < self.gcfg.min_mask_similarity:
            res.message = (f"no part of the map looks like {r.target!r}: best mask similarity {msim:.2f} "
                           f"< {self.gcfg.min_mask_similarity}")
            res.timings = t
            return res
        res.reference_view, res.scale = kf.index, scale

        t2 = time.perf_counter()
        w, h = kf.size
        fr = self.render_keyframe(kf)
        canon = self.encode(list(CANONICAL))
        # Features bleed a pixel or two over object borders: take the peak of the 3x3 mean, and
        # inside the reference mask (the 2D evidence that chose s*) when it has rendered pixels.
        # Relevancy is computed only over the mask's box grown by 2 pixels (the 3x3 mean of a mask
        # pixel reads nothing beyond): the same peak as over the whole view, in a fraction of the time.
        ref_mask = torch.from_numpy(self.mapper.supervision.by_keyframe[kf.index].masks[mi])
        in_mask = ref_mask.shape == (h, w) and bool((ref_mask & (fr.alpha > self.gcfg.mask_alpha)).any())
        y0, y1, x0, x1 = 0, h, 0, w
        if in_mask:
            ys, xs = torch.nonzero(ref_mask, as_tuple=True)
            y0, y1 = max(int(ys.min()) - 2, 0), min(int(ys.max()) + 3, h)
            x0, x1 = max(int(xs.min()) - 2, 0), min(int(xs.max()) + 3, w)
        rel = self._relevancy(fr, r.target, scale, (slice(y0, y1), slice(x0, x1)))  # [y1-y0, x1-x0]
        smooth = torch.nn.functional.avg_pool2d(rel[None, None], 3, 1, 1, count_include_pad=False)[0, 0]
        if in_mask:
            smooth = torch.where(ref_mask[y0:y1, x0:x1], smooth, torch.full_like(smooth, -1.0))
        peak = int(smooth.reshape(-1).argmax())
        py, px = divmod(peak, x1 - x0)
        peak_rel = float(rel[py, px])
        py, px = py + y0, px + x0
        q_inst = self.field.instance(fr.latent[py, px], scale)                # [Di]
        t["relevancy"] = time.perf_counter() - t2

        t3 = time.perf_counter()
        # Leave out what the query does not need: one object is sought near the reference mask.
        region = self.region(kf, ref_mask.numpy(), fr.depth, fr.alpha, scale) if max_results == 1 else None
        groups = self.groups(scale, region)
        t["cluster"] = time.perf_counter() - t3
        t4 = time.perf_counter()
        sim = groups.centres @ q_inst                                          # [G]
        order = torch.argsort(sim, descending=True).tolist()
        home = groups.containing(q_inst)
        if home >= 0:
            order.remove(home)
            order.insert(0, home)
        chosen = [order[0]] if order else []
        if max_results > 1 and order:
            chosen = self._more_instances(groups, order, target, canon, scale, max_results)
        g = self.mapper.gaussians
        means, colors = g.means.detach().numpy(), (g.colors.detach().clamp(0, 1) * 255).round().byte().numpy()
        found = []
        if home < 0:
            # The most relevant pixel's feature lies in no cluster: HDBSCAN left that object as noise.
            # Its group is then the Gaussians around that feature (as tight as a typical cluster).
            # Too few there (a weakly trained field): the nearest cluster, or with no cluster at all
            # the 2 x min_cluster_size Gaussians nearest that feature.
            ball = groups.ball(q_inst)
            mcs = self.gcfg.min_cluster_size
            if len(ball) >= mcs:
                found.append((ball, float(sim.max()) if len(sim) else 1.0))
                chosen = chosen[1:] if max_results > 1 else []
            elif not chosen and groups.features is not None and len(groups.features):
                d = groups.features @ torch.nn.functional.normalize(q_inst.float(), dim=-1)
                near = torch.topk(d, min(2 * mcs, len(d))).indices.numpy()
                found.append((np.sort(near), float(d[near].mean())))
        found += [(groups.members(gi, grow=self.gcfg.grow_groups), float(max(sim[gi], 0.0))) for gi in chosen]
        link = self.gcfg.link_spacing * self.spacing()
        z = float(fr.depth[py, px] / fr.alpha[py, px].clamp(min=1e-6))             # the surface there
        anchor = pixels_to_points(px, py, z, np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64))
        views = self.carve_views(cands)
        ref_view = None
        if self.gcfg.anchor_support and ref_mask.shape == tuple(kf.depth.shape):
            ref_view = MaskView(np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64),
                                kf.depth.numpy(), ref_mask.numpy())
        carved = voted = None
        border = self.vote_border() if views or ref_view is not None else 0
        if views:
            # Votes only where they can matter: the groups and what lies within 4 s* of the peak.
            near = np.nonzero(np.linalg.norm(means - anchor, axis=1) <= 4 * scale)[0] if z > 0 else np.zeros(0, np.int64)
            cand = np.unique(np.concatenate([ids for ids, _ in found[:max_results]] + [near]).astype(np.int64))
            v = mask_votes(means[cand], views, g.scales.detach()[torch.from_numpy(cand)].max(1).values.numpy(),
                           border_px=border)
            carved, voted = np.zeros(len(means), bool), np.zeros(len(means), bool)
            carved[cand], voted[cand] = v.carved(self.gcfg.min_mask_votes), v.voted(self.gcfg.min_mask_votes)
        for n, (ids, s_g) in enumerate(found[:max_results]):
            if carved is not None:
                # Carve what the target's masks see elsewhere; the first group also takes what
                # several of them see inside (HDBSCAN splits a weakly trained object into pieces).
                ids = ids[~carved[ids]]
                if n == 0:
                    ids = np.union1d(ids, np.nonzero(voted)[0])
            if link > 0 and len(ids) > 1:  # the first group holds the most relevant point; others their largest piece
                support = None
                if n == 0 and ref_view is not None:
                    # The piece the reference mask sees most, not only the one under its peak pixel.
                    support = mask_votes(means[ids], [ref_view], g.scales.detach()[torch.from_numpy(ids)]
                                         .max(1).values.numpy(), border_px=border).inside > 0
                ids = ids[connected_to(means[ids], anchor if n == 0 and z > 0 else None, link, support)]
            ids = ids[robust_inliers(means[ids], self.gcfg.outlier_mads)]
            if not len(ids):
                continue
            lo, hi, c, R, ext = group_boxes(means[ids])
            conf = float(r.confidence) * peak_rel * s_g
            res.objects.append(GroundedObject(ids.astype(np.int64), means[ids].astype(np.float32), colors[ids],
                                              lo, hi, c, R, ext, conf))
        t["group"] = time.perf_counter() - t4
        t["total"] = time.perf_counter() - t0
        res.timings = t
        if not res.objects:
            res.message = (f"no Gaussian group for {r.target!r} at scale {scale:.3f} m: HDBSCAN found "
                           f"{len(groups.centres)} groups and none held the most relevant pixel's feature")
            return res
        res.success = True
        res.confidence = res.objects[0].confidence
        res.message = (f"{len(res.objects)} group(s) for {r.target!r}, {len(res.objects[0].gaussian_ids)} Gaussians; "
                       f"reference view {kf.index}, scale {scale:.3f} m")
        res.explanation = (f"{r.explanation} Reference view {kf.index} (mask similarity {msim:.2f}); scale "
                           f"{scale:.3f} m; the most relevant pixel ({px}, {py}, relevancy {peak_rel:.2f}) lies in "
                           f"a group of {len(res.objects[0].gaussian_ids)} Gaussians.")
        return res

    @torch.no_grad()
    def relevancy_view(self, target: str, scale: float, K, cam_to_world, width: int, height: int):
        """Relevancy [h, w] of `target` at `scale` from any camera (0 where the map is not opaque),
        and the field render it came from."""
        fr = self.field.render(K, cam_to_world, width, height)
        return self._relevancy(fr, target, scale), fr

    def _relevancy(self, fr, target: str, scale: float, window=(slice(None), slice(None))) -> torch.Tensor:
        """Relevancy of `target` over a window (rows, cols slices) of a field render: [h', w'],
        0 where the map is not opaque."""
        pca = self.mapper.supervision.pca.pca
        alpha = fr.alpha[window]
        rel = relevancy_pca(self.field.language(fr.latent[window], scale), pca.components, pca.mean,
                            self.encode([target])[0], self.encode(list(CANONICAL)))
        return torch.where(alpha > self.gcfg.mask_alpha, rel, torch.zeros_like(rel))

    def _more_instances(self, groups: Groups, order: list[int], target, canon, scale, k: int) -> list[int]:
        """Other groups as relevant as the best one ("the cups"): relevancy of each group's mean latent."""
        lat = self.field.latents
        labels = torch.from_numpy(groups.labels)
        scores = []
        for gi in order:
            members = labels == gi
            if not bool(members.any()):
                scores.append(0.0)
                continue
            z = self.field.language(lat[members].mean(0), scale)
            scores.append(float(relevancy(self._decompress(z), target, canon)))
        best = scores[0]
        chosen = [order[0]]
        for gi, s in sorted(zip(order[1:], scores[1:]), key=lambda x: -x[1]):
            if len(chosen) >= k:
                break
            if s >= self.gcfg.multi_instance_ratio * best and s > 0.5:
                chosen.append(gi)
        return chosen

    # ------------------------------------------------------------------------------ masks

    @torch.no_grad()
    def masks(self, result: GroundingResult, K: np.ndarray, cam_to_world: np.ndarray, width: int,
              height: int) -> tuple[np.ndarray, np.ndarray]:
        """Amodal (the group rendered alone) and visible (the group's share of the blending weight
        in the full render above one half) masks of a result's groups: two bool [height, width]."""
        g = self.mapper.gaussians
        N = len(g)
        empty = np.zeros((height, width), bool)
        ids = np.concatenate([o.gaussian_ids for o in result.objects]) if result.objects else np.zeros(0, np.int64)
        if not result.success or not len(ids) or not N:
            return empty, empty.copy()
        if int(ids.max()) >= N:
            raise ValueError(f"masks: the result names Gaussian {int(ids.max())} but the map now has {N}; ground again")
        cam = self.mapper.camera(K, cam_to_world, width, height)
        member = torch.zeros(N, 1)
        member[torch.from_numpy(ids)] = 1.0
        args = (g.means.detach(), g.scales.detach(), g.quats.detach(), g.opacities.detach())
        full = rasterize(*args, member, cam)
        alone = rasterize(*args, member, cam, subset=torch.from_numpy(ids))
        a = self.gcfg.mask_alpha
        share = full.channels[..., 0] / full.alpha.clamp(min=1e-6)
        visible = (full.alpha > a) & (share > 0.5)
        amodal = alone.alpha > a
        return amodal.numpy(), visible.numpy()
