"""The query pipeline in the paper's order: reasoning -> reference view -> relevancy -> scale s* ->
HDBSCAN over instance features at s* -> the group under the most relevant pixel -> boxes.

`Grounder` holds no map state of its own: it reads the Mapper (keyframes, Gaussians, supervision)
and the FeatureField, so a node can keep mapping and training between queries.
"""
from __future__ import annotations

import dataclasses
import hashlib
import logging
import time

import numpy as np
import torch

from ..config import RGConfig
from ..field.converge import describe
from ..geometry.conventions import backproject, up_direction
from ..geometry.points import map_spacing, within
from ..render import rasterize
from ..util import torch_threads
from . import confidence, phrases, relations, stages
from .cache import MapCache
from .carve import mask_depth_offsets, registration_border
from .grouping import Groups, cluster_instances
from .masks import leave_occluded, refine_visible, snap_to_image, surfaces_apart
from .relevancy import CANONICAL, relevancy_pca
from ..perception.query import parse_mode, query_problem
from ..perception.text_cache import inner_encoder
from .result import GroundingResult
from .vocabulary import build_vocabulary, looks_like_name

log = logging.getLogger(__name__)
TEXT_CACHE_SIZE = 4096   # query and name embeddings kept per Grounder (1.5 KB each)


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

    @classmethod
    def from_map(cls, mapper, cfg: RGConfig | None = None, field=None, text_encoder=None, reasoner=None,
                 scene_names: list[str] | None = None, source: str = "the map") -> "Grounder":
        """The one way callers assemble a Grounder (rg ground, rg map, the node's worker, build.py):
        over `mapper` and its field (or `field`). With a text encoder, the map's mask embeddings
        must have its width: a map built with another preset cannot be queried (ValueError)."""
        sset = getattr(mapper, "supervision", None)
        embs = [s.embeddings for s in sset.by_keyframe.values() if len(s.embeddings)] if sset is not None else []
        if text_encoder is not None and embs:
            d_map, d_text = embs[0].shape[-1], text_encoder(["x"]).shape[-1]
            if d_map != d_text:
                raise ValueError(f"{source}: the map's embeddings are {d_map}-d, the text encoder embeds queries in "
                                 f"{d_text}-d: ground with the preset the map was built with")
        return cls(mapper, field if field is not None else getattr(mapper, "field", None), cfg, reasoner=reasoner,
                   text_encoder=text_encoder, scene_names=scene_names)

    # ------------------------------------------------------------------------------ models

    @property
    def reasoner(self):
        if self._reasoner is None:
            from ..perception.reasoning import reasoner_from_config

            self._reasoner = reasoner_from_config(self.cfg.reason)
        return self._reasoner

    def text_model(self):
        """The text encoder queries are embedded with (the packaged MiniLM unless one was given)."""
        if self._text is None:
            from ..perception.embed import MiniLMText

            self._text = MiniLMText()
        return self._text

    def load_models(self) -> "Grounder":
        """Load the reasoner's and the text encoder's models now rather than in the first query that
        needs one (0.1-0.3 s): what a long-running node does at start. `rg ground`, a process per
        query, skips it: a query whose texts the map stores needs no text model at all."""
        self.reasoner.load()
        load = getattr(inner_encoder(self.text_model()), "load", None)
        if load is not None:
            load()
        return self

    def encode(self, texts: list[str]) -> torch.Tensor:
        """[n] strings -> [n, D] unit rows (cached: canonical phrases and names repeat)."""
        self.text_model()
        todo = [t for t in dict.fromkeys(texts) if t not in self._text_cache]
        if todo:
            for t, e in zip(todo, self._text(todo)):
                self._text_cache[t] = torch.nn.functional.normalize(e.float(), dim=-1)
        out = torch.stack([self._text_cache[t] for t in texts]) if texts else torch.zeros(0, 1)
        while len(self._text_cache) > TEXT_CACHE_SIZE:   # hours of distinct queries: the oldest go
            self._text_cache.pop(next(iter(self._text_cache)))
        return out

    def store_texts(self) -> int:
        """Embed the texts a query on this map needs besides the query itself (household, scene and
        configured names, their reasoner prompt form, the reasoner's background names, the canonical
        phrases) with MiniLM and keep them in the map's supervision: save_map then stores them, and
        a new process answers a query naming one of them without loading the text model. -> count."""
        from ..perception import reasoning as rmod
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
        """Empty the cache tables whose map, supervision or field state changed since they were
        filled (rg_core/grounding/cache.py: scopes)."""
        m, f = self.mapper, self.field
        g = m.gaussians
        sset = m.supervision
        sup = (len(m.keyframes), m.keyframes[-1].index if m.keyframes else -1, id(sset))
        if sset is not None:
            sup += (len(sset.by_keyframe), sum(len(s.embeddings) for s in sset.by_keyframe.values()),
                    getattr(sset.pca, "version", None), id(sset.pca.pca))
        tensors = (g.means, g.log_scales, g.quats, g.opacity_logits)
        rows: tuple = ()
        if f is not None:
            if len(f.latents) != len(g):
                f.sync()  # latents follow Gaussians added or pruned since the last training step
            tensors += (f.latents,)
            rows = (id(f), f.revision, f.steps, f._pca[0] if getattr(f, "_pca", None) is not None else None,
                    id(f.scale_tf))
        scopes = {"map": (tensors, (len(g),) + sup + rows), "supervision": ((), sup),
                  "field": ((f,) if f is not None else (), rows)}
        self.cache.check(scopes)

    # ------------------------------------------------------------------------------ checks

    def _not_ready(self) -> str | None:
        m = self.mapper
        if not m.keyframes or not len(m.gaussians):
            return "the map is empty: no keyframes yet"
        if m.supervision is None or not m.supervision.by_keyframe or m.supervision.pca.pca is None:
            return "the map has no 2D supervision yet (masks and embeddings per keyframe)"
        if self.field is None or self.field.steps == 0:
            return "the feature field has not been trained yet"
        if getattr(self.field, "stop", True) is None:
            return (f"the feature field is still training ({self.field.steps} steps): it answers once its "
                    f"held-out accuracy converged or its budget ran out")
        return None

    # ------------------------------------------------------------------------------ map-derived data

    def groups(self, scale: float, region: np.ndarray | None = None) -> Groups:
        """Clusters of instance features at one scale, over the Gaussians in `region` (bool [N];
        None: all); cached until the map, the field or the region changes. Gaussians outside the
        region are left out (rows only for the region's Gaussians: Groups.ids), so they never join a group."""
        self._check_cache()
        N = len(self.mapper.gaussians)
        key = (round(scale, 4), N, None if region is None else np.packbits(region).tobytes())

        def cluster(idx: torch.Tensor | None) -> Groups:
            g = self.gcfg
            with torch_threads(self._outer_threads):
                feats = self.field.gaussian_instance(scale, idx)                # [N or M, Di]: the region's only
            return cluster_instances(feats, g.max_cluster_points, g.min_cluster_size, g.cluster_eps,
                                     seed=g.seed, method=g.cluster_method)

        def make() -> Groups:
            if region is None:
                return cluster(None)
            idx = np.nonzero(region)[0]                                         # [M]
            # The region's clusters depend on its Gaussians' field rows only: kept while the map grows
            # elsewhere (appended rows leave old ones as they were; cache.py, scope "field").
            digest = hashlib.blake2b(idx.astype(np.int64).tobytes(), digest_size=16).digest()
            sub = self.cache.get("clusters", (round(scale, 4), len(idx), digest),
                                 lambda: cluster(torch.from_numpy(idx)))
            return dataclasses.replace(sub, ids=idx)
        return self.cache.get("groups", key, make)

    def region(self, kf, mask: np.ndarray, depth: torch.Tensor, alpha: torch.Tensor, scale: float) -> np.ndarray | None:
        """Gaussians that can belong to the reference mask's object: within `region_scales` x s* of
        the 3D centroid of the mask (back-projected with the rendered depth), else within
        `cull_radius` m of it when that leaves out > 10 % of the map. None: all (no depth there)."""
        g = self.gcfg
        if (g.region_scales <= 0 and g.cull_radius <= 0) or mask.shape != tuple(depth.shape):
            return None
        sel = torch.from_numpy(mask) & (alpha > self.gcfg.mask_alpha) & (depth > 0)
        if int(sel.sum()) < 3:
            return None
        pts = backproject(depth.numpy(), np.asarray(kf.K, np.float64), np.asarray(kf.cam_to_world, np.float64))
        centre = np.median(pts[sel.numpy()], 0)                                        # [3] world
        means = self.mapper.gaussians.means.detach()
        r = g.region_scales * max(scale, 1e-3) if g.region_scales > 0 else g.cull_radius
        near = np.zeros(len(means), bool)
        near[within(means, centre, r)] = True
        return near if g.region_scales > 0 or g.min_cluster_size <= near.sum() < 0.9 * len(near) else None

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
            with torch_threads(self._outer_threads):
                return self.field.render(kf.K, kf.cam_to_world, w, h)
        return self.cache.get("renders", (kf.index, w, h), make)

    def _decompress(self, z: torch.Tensor) -> torch.Tensor:  # [..., k] -> [..., D]
        return self.mapper.supervision.pca.pca.inverse(z)

    def ground(self, query: str, mode: str = "auto", max_results: int = 1,
               cam_to_world: np.ndarray | None = None, camera: str = "the query's camera") -> GroundingResult:
        """`cam_to_world` [4, 4]: the camera view-dependent words ("left of", "nearest to me") refer
        to, named `camera` in the explanation; None: the newest keyframe."""
        self._outer_threads = torch.get_num_threads()
        with torch_threads(self.gcfg.query_threads):
            return self._ground(query, mode, max_results, None if cam_to_world is None else (cam_to_world, camera))

    def scene_graph(self) -> list:
        """The map's objects (relations.build_graph over the vocabulary), cached with the map."""
        self._check_cache()
        names = self.vocabulary()
        return self.cache.get("graph", tuple(names), lambda: relations.build_graph(self, names))

    def up(self) -> np.ndarray:
        """The map's up direction [3] from its keyframes' poses (geometry.conventions.up_direction)."""
        self._check_cache()
        return self.cache.get("up", tuple(k.index for k in self.mapper.keyframes),
                              lambda: up_direction(np.stack([k.cam_to_world for k in self.mapper.keyframes])))

    def _relational(self, rq, objs: list, query: str, max_results: int, view: tuple | None,
                    t: dict, t0: float) -> GroundingResult:
        """Over the scene graph `objs`; `view` = (cam_to_world, its name) or None (the newest keyframe)."""
        if view is None:
            kf = self.mapper.keyframes[-1]
            view = kf.cam_to_world, f"keyframe {kf.index}, the newest"
        cam_to_world, camera = view
        res = relations.answer(rq, objs, np.asarray(cam_to_world, np.float64), camera, max_results, query, self.up())
        t["total"] = time.perf_counter() - t0
        res.timings = t
        return res

    def _ground(self, query: str, mode: str, max_results: int, view: tuple | None = None) -> GroundingResult:
        t0 = time.perf_counter()
        bad = query_problem(query, self.gcfg.max_query_chars)
        if bad:
            return GroundingResult(False, bad, query=str(query)[:200])
        try:
            mode = parse_mode(mode)
        except ValueError as exc:
            return GroundingResult(False, str(exc), query=query)
        if max_results < 1:
            return GroundingResult(False, f"max_results must be >= 1, got {max_results}", query=query)
        not_ready = self._not_ready()
        if not_ready:
            return GroundingResult(False, not_ready, query=query)
        self._check_cache()
        name = phrases.bare_name(query, self.vocabulary())
        if name is not None and name != query:   # "the orange cup, please": that name, the usual path
            res = self._ground(name, mode, max_results, view)
            res.query = query
            return res
        rq = None
        if mode != "explicit" and name is None:
            rq = phrases.parse_with(self.reasoner, query)[0] if self.cfg.reason.llm_parse else phrases.parse(query)
        if rq is not None:   # about objects in relation to others: over the scene graph
            s = time.perf_counter()
            objs = self.scene_graph()
            if relations.for_graph(rq, objs):
                return self._relational(rq, objs, query, max_results, view, {"graph": time.perf_counter() - s}, t0)
        t: dict[str, float] = {}
        res = GroundingResult(False, "", query=query)
        res.timings = t

        def timed(stage, fn, *args):
            s = time.perf_counter()
            out = fn(*args)
            t[stage] = time.perf_counter() - s
            return out

        r = self._reason(query, mode)
        t["reason"] = time.perf_counter() - t0   # from the start: validation is part of it
        res.target, res.explanation = r.target, r.explanation
        if not r.target:
            res.message = f"nothing in the map matches {query!r}: {r.explanation}"
            return res
        ref = timed("reference_view", stages.reference, self, r.target)
        if isinstance(ref, str):
            res.message = ref
            return res
        res.reference_view, res.scale = ref.keyframe.index, ref.scale
        pk = timed("relevancy", stages.peak, self, ref, r.target)
        groups, found = timed("cluster", stages.candidate_groups, self, ref, pk, max_results)
        res.objects = timed("group", stages.objects, self, ref, pk, found, max_results, r.confidence)
        t["total"] = time.perf_counter() - t0
        if not res.objects:
            res.message = (f"no Gaussian group for {r.target!r} at scale {ref.scale:.3f} m: HDBSCAN found "
                           f"{len(groups.centres)} groups and none held the most relevant pixel's feature")
            return res
        kf, first = ref.keyframe.index, res.objects[0]
        n = len(first.gaussian_ids)
        sure, why = timed("confidence", confidence.assess, self, res, r, ref, pk, found[0][1])
        res.success = sure
        where = "({:.2f}, {:.2f}, {:.2f})".format(*first.obb_center)
        res.message = (f"{len(res.objects)} group(s) for {r.target!r}, {n} Gaussians; reference view {kf}, "
                       f"scale {ref.scale:.3f} m" if sure else
                       f"not sure the answer is {r.target!r}: {why}; best guess {n} Gaussians at {where} m")
        res.explanation = (f"{r.explanation} Reference view {kf} (mask similarity {ref.similarity:.2f}); scale "
                           f"{ref.scale:.3f} m; the most relevant pixel ({pk.px}, {pk.py}, relevancy "
                           f"{pk.relevancy:.2f}) lies in a group of {n} Gaussians. Confidence {res.confidence:.2f}"
                           f"{'' if sure else ': not sure, ' + why}. {describe(self.field.stop, self.field.steps)}.")
        t["field_training"] = float(self.field.stop["seconds"])  # the training behind this answer (not in total)
        return res

    def _reason(self, query: str, mode: str):
        """The reasoner's target for the query. An LVLM sees the scene (the paper's reference view:
        the target is not known yet, so a few keyframes spread over the map); text reasoners and
        explicit queries need no picture."""
        vocab = self.vocabulary()
        if mode != "implicit" and looks_like_name(query) and query.strip() not in vocab:
            vocab.append(query.strip())
        image = self.scene_image() if mode != "explicit" and getattr(self.reasoner, "accepts_images", False) else None
        return self.reasoner.reason(query, vocab, image=image, mode=mode)

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

    # ------------------------------------------------------------------------------ masks

    def masks(self, result: GroundingResult, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
              depth: np.ndarray | None = None, image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Amodal (the group rendered alone) and visible (the group's share of the blending weight
        in the full render above `ground.visible_share`) masks of a result's groups, also of an
        abstained answer's best guess: two bool [height, width]. With the camera's depth image
        (`depth` [height, width] metres) the visible mask follows it (`ground.visible_depth_tol`), and
        with its colour image (`image` [height, width, 3]) its rim snaps to the colour edges
        (`ground.visible_edge_eps`)."""
        amodal, visible, sensed = self.mask_layers(result, K, cam_to_world, width, height, depth, image)
        return amodal, visible if sensed is None else sensed

    @torch.no_grad()
    def mask_layers(self, result: GroundingResult, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
                    depth: np.ndarray | None = None,
                    image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """`masks` from one set of renders: amodal, visible as rendered, and visible following the
        camera's `depth` and `image` (None without either): what `rg eval` scores side by side."""
        g = self.mapper.gaussians
        N = len(g)
        empty = np.zeros((height, width), bool)
        sensed = depth is not None or image is not None
        ids = np.concatenate([o.gaussian_ids for o in result.objects]) if result.objects else np.zeros(0, np.int64)
        if not len(ids) or not N:
            return empty, empty.copy(), empty.copy() if sensed else None
        if int(ids.max()) >= N:
            raise ValueError(f"masks: the result names Gaussian {int(ids.max())} but the map now has {N}; ground again")
        cam = self.mapper.camera(K, cam_to_world, width, height)
        member = torch.zeros(N, 1)
        member[torch.from_numpy(ids)] = 1.0
        args = (g.means.detach(), g.scales.detach(), g.quats.detach(), g.opacities.detach())
        aa = self.mapper.cfg.antialiased
        full = rasterize(*args, member, cam, antialiased=aa)
        alone = rasterize(*args, member, cam, subset=torch.from_numpy(ids), antialiased=aa)
        a = self.gcfg.mask_alpha
        share = full.channels[..., 0] / full.alpha.clamp(min=1e-6)
        visible = ((full.alpha > a) & (share > self.gcfg.visible_share)).numpy()
        amodal = (alone.alpha > a).numpy()
        if not sensed:
            return amodal, visible, None
        out = visible.copy()
        apart = None
        if depth is not None and self.gcfg.visible_depth_tol > 0:
            others = torch.ones(N, dtype=torch.bool)
            others[torch.from_numpy(ids)] = False
            rest = rasterize(*args, member, cam, subset=others, antialiased=aa)
            out = refine_visible(visible, alone.alpha.numpy(), alone.depth.numpy(), rest.alpha.numpy(),
                                 rest.depth.numpy(), depth, self.gcfg.visible_depth_tol)
            apart = surfaces_apart(alone.alpha.numpy(), alone.depth.numpy(), rest.alpha.numpy(), rest.depth.numpy(),
                                   self.gcfg.visible_depth_tol)
        if depth is not None and (self.gcfg.visible_front_tol > 0 or apart is not None):
            out = leave_occluded(out, depth, alone.alpha.numpy(), alone.depth.numpy(), K, cam_to_world, args,
                                 member[:, 0].numpy() > 0, self.gcfg.visible_front_tol or np.inf,
                                 rim_ratio=self.gcfg.visible_rim_ratio if apart is not None else 0.0,
                                 rim_where=apart)
        if image is not None and self.gcfg.visible_edge_eps > 0:
            out = snap_to_image(out, image, eps=self.gcfg.visible_edge_eps)
        return amodal, visible, out
