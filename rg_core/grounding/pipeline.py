"""The query pipeline in the paper's order: reasoning -> reference view -> relevancy -> scale s* ->
HDBSCAN over instance features at s* -> the group under the most relevant pixel -> boxes.

`Grounder` holds no map state of its own: it reads the Mapper (keyframes, Gaussians, supervision)
and the FeatureField, so a node can keep mapping and training between queries. What it derives from
the map is in derived.py (kept in cache.py's MapCache), text embeddings in texts.py, masks of a
result in masks.py.
"""
from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import torch

from ..config import RGConfig
from ..field.converge import describe
from ..util import torch_threads
from . import confidence, derived, phrases, relations, stages, teach
from .cache import MapCache, map_scopes
from .grouping import Groups
from .masks import result_masks
from .relevancy import CANONICAL, relevancy_pca
from ..perception.query import parse_mode, query_problem
from ..perception.text_cache import inner_encoder
from .result import GroundingResult
from .texts import encode_kept, store_texts
from .vocabulary import looks_like_name

log = logging.getLogger(__name__)


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
        self._text_cache: dict[str, torch.Tensor] = {}   # texts.encode_kept
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
        """Load the reasoner's and the text encoder's models and the clustering library now rather than
        in the first query that needs one (0.1-0.3 s, HDBSCAN's import 0.9 s): what a long-running node does at start. `rg ground`, a process per
        query, skips it: a query whose texts the map stores needs no text model at all."""
        self.reasoner.load()
        load = getattr(inner_encoder(self.text_model()), "load", None)
        if load is not None:
            load()
        import sklearn.cluster  # noqa: F401 - HDBSCAN's import: 0.9 s, once per process
        return self

    # ------------------------------------------------------------------------------ texts (texts.py)

    def encode(self, texts: list[str]) -> torch.Tensor:
        """[n] strings -> [n, D] unit rows (cached: canonical phrases and names repeat; texts.py)."""
        return encode_kept(self.text_model(), self._text_cache, texts)

    def store_texts(self) -> int:
        """Embed and keep in the map's supervision the texts a query on this map needs besides the
        query itself, so a new process answers one naming them without the text model (texts.py). -> count."""
        return store_texts(self)

    # ------------------------------------------------------------------------------ checks

    def _check_cache(self) -> None:
        """Empty the cache tables whose map, supervision or field state changed since they were
        filled (rg_core/grounding/cache.py: scopes)."""
        self.cache.check(map_scopes(self.mapper, self.field))

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

    # ------------------------------------------------------------------------------ map-derived data (derived.py)

    def scene_image(self, max_views: int = 4) -> np.ndarray:
        """-> [H, W, 3] uint8 RGB: up to `max_views` keyframes tiled 2 x 2, what an image reasoner is
        shown of the scene (derived.scene_image)."""
        return derived.scene_image(self, max_views)

    def vocabulary(self) -> list[str]:
        """The names a reasoner may pick from, cached with the supervision (derived.vocabulary)."""
        return derived.vocabulary(self)

    def groups(self, scale: float, region: np.ndarray | None = None) -> Groups:
        """Clusters of instance features at one scale over the Gaussians in `region` (bool [N]; None: all)."""
        return derived.groups(self, scale, region)

    def region(self, kf, mask: np.ndarray, depth: torch.Tensor, alpha: torch.Tensor, scale: float) -> np.ndarray | None:
        """Gaussians that can belong to the reference mask's object (bool [N]; None: all)."""
        return derived.region(self, kf, mask, depth, alpha, scale)

    def spacing(self) -> float:
        """The map's median nearest-neighbour distance between Gaussians (m)."""
        return derived.spacing(self)

    def link_length(self) -> float:
        """Longest step (m) of the links that keep a group one piece in space (0: none)."""
        return derived.link_length(self)

    def vote_border(self) -> int:
        """Mask growth (px) for the votes: ground.vote_border_px, or measured with -1."""
        return derived.vote_border(self)

    def vote_depth_tol(self) -> float:
        """Least depth difference (m) at which the votes call a Gaussian off a keyframe's surface."""
        return derived.vote_depth_tol(self)

    def render_keyframe(self, kf):
        """The field rendered from a keyframe (latent, colour, depth, alpha), cached per keyframe."""
        return derived.render_keyframe(self, kf)

    def mask_points(self, kf, j: int, at_most: int) -> np.ndarray:
        """[P, 3] world points of keyframe `kf`'s supervision mask j (stages.mask_points), cached."""
        return derived.mask_points(self, kf, j, at_most)

    def scene_graph(self) -> list:
        """The map's objects (relations.build_graph over the vocabulary), cached with the map."""
        return derived.scene_graph(self)

    def up(self) -> np.ndarray:
        """The map's up direction [3] from its keyframes' poses."""
        return derived.up(self)

    def _decompress(self, z: torch.Tensor) -> torch.Tensor:  # [..., k] -> [..., D]
        return self.mapper.supervision.pca.pca.inverse(z)

    def ground(self, query: str, mode: str = "auto", max_results: int = 1,
               cam_to_world: np.ndarray | None = None, camera: str = "the query's camera") -> GroundingResult:
        """`cam_to_world` [4, 4]: the camera view-dependent words ("left of", "nearest to me") refer
        to, named `camera` in the explanation; None: the newest keyframe."""
        self._outer_threads = torch.get_num_threads()
        with torch_threads(self.gcfg.query_threads):
            return self._ground(query, mode, max_results, None if cam_to_world is None else (cam_to_world, camera))

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
        """_answer, kept while the map, field and config are unchanged (cache table "answers"): asked
        again (a repeated /ground, the confidence check of clicks the map names alike) it costs a
        lookup. A kept answer's timings are those of its computation, with this call's "total" and
        "cached" (s)."""
        t0 = time.perf_counter()
        if self._not_ready():
            return self._answer(query, mode, max_results, view)
        self._check_cache()
        where = None if view is None else (np.asarray(view[0], np.float64).tobytes(), str(view[1]))
        key = (str(query), str(mode), int(max_results), where, repr(self.cfg), tuple(self.scene_names))
        misses = self.cache.misses
        res = self.cache.get("answers", key, lambda: self._answer(query, mode, max_results, view))
        # Callers edit what they get: a new result with its own lists and dicts, the same objects
        # (the scene graph's own where the answer is from it; nothing edits an answer's objects).
        res = dataclasses.replace(res, objects=list(res.objects), timings=dict(res.timings),
                                  evidence=dict(res.evidence), names=list(res.names),
                                  point=None if res.point is None else list(res.point))
        if self.cache.misses == misses:   # kept: this call was a lookup (computing it misses at least once)
            dt = time.perf_counter() - t0
            res.timings.update(total=dt, cached=dt)
        return res

    def _answer(self, query: str, mode: str, max_results: int, view: tuple | None = None) -> GroundingResult:
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
        if len(self.mapper.taught):   # a person's names first (teach.py)
            taught = teach.answer_query(self, query, max_results)
            if taught is not None:
                taught.timings = {"total": time.perf_counter() - t0}
                return taught
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
            if relations.for_graph(rq, objs, self.vocabulary()):   # with the query's names the graph lacks
                objs = relations.with_query_names(self, rq, objs)
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
        taught = teach.answer(self, r.target, max_results, r.explanation) if r.target else None
        if taught is not None:   # the reasoner picked a taught name (or a variant: 'mug' for 'blue mug')
            taught.query, taught.timings = query, {**t, "total": time.perf_counter() - t0}
            return taught
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
    def relevancy_view(self, target: str, scale: float, K, cam_to_world, width: int, height: int, render=None):
        """Relevancy [h, w] of `target` at `scale` from any camera (0 where the map is not opaque),
        and the field render it came from (`render`: that camera's field render, to reuse)."""
        fr = self.field.render(K, cam_to_world, width, height) if render is None else render
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

    def mask_layers(self, result: GroundingResult, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
                    depth: np.ndarray | None = None,
                    image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """`masks` from one set of renders: amodal, visible as rendered, and visible following the
        camera's `depth` and `image` (None without either): what `rg eval` scores side by side."""
        return result_masks(self.mapper, self.gcfg, result, K, cam_to_world, width, height, depth, image)
