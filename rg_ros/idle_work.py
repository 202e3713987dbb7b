"""The map worker's background work while no frame waits, one small slice per step, in this order:
supervision of new keyframes (masks + embeddings), feature-field training (`train_slice` seconds at
a time, capped at `train_seconds_max` after each supervision change), loading the grounding models
once the field first answers, then map refinement. The perception models (mask generator,
embedder; ~10 s to load) load in a helper thread started with the worker, so mapping never waits."""
from __future__ import annotations

import time
from typing import Any

from rg_core.field.converge import describe


class IdleWork:
    """Mixin of MapWorker: its idle steps and the perception loader. Uses the worker's config
    (cfg, wcfg), map (mapper, field), lock, queue, log, caller_waits and _ensure_grounder, and the
    state MapWorker.__init__ sets (_perception, perception_state, _train_seconds, ...)."""

    def _idle_step(self) -> bool:
        """One slice of background work; False if there was nothing to do."""
        if self.wcfg.features and self._perception is not None and self._supervise():
            return True
        if self.wcfg.features and self._train():
            return True
        if self.wcfg.features and self._load_models():
            return True
        return self._refine()

    def _load_models(self) -> bool:
        """Once the field first answers: the Grounder and its models (reasoner, text encoder), made
        here rather than in the first query. One step; a failure is logged and left to that query."""
        if self._models_loaded or self.field is None or self.field.stop is None:
            return False
        t = time.perf_counter()
        with self.lock:
            try:
                self._ensure_grounder().load_models()
                with self.read_lock:   # the readers' Grounder takes the loaded models
                    self._reader_for(self._snap)
                    self._share_models()
                self.log.info("grounding models loaded ahead of the first query (%.2f s)", time.perf_counter() - t)
            except Exception as exc:  # noqa: BLE001 - the first query says what is missing
                self.log.warning("grounding models not loaded ahead: %s: %s", type(exc).__name__, exc)
            finally:
                self._models_loaded = True   # tried once (diagnostics: grounding_models)
        return True

    def _supervise(self) -> bool:
        with self.lock:
            sset = getattr(self.mapper, "supervision", None)
            done = set(sset.by_keyframe) if sset is not None else set()
            if all(kf.index in done for kf in self.mapper.keyframes):
                return False
            from rg_core.perception.supervision import supervise_map_multiview

            gen, emb = self._perception
            t = time.perf_counter()
            try:
                sset, mv = supervise_map_multiview(self.mapper, gen, emb,
                                                   views_per_object=self.cfg.models.views_per_object,
                                                   between=self._give_way)
            except Exception as exc:  # noqa: BLE001 - a perception failure must not stop mapping
                self.log.error("supervision failed, feature training is off: %s: %s", type(exc).__name__, exc)
                self.wcfg.features = False
                self.perception_state = f"failed: supervision: {type(exc).__name__}: {exc}"
                return False
            if len(self.mapper.taught):   # new keyframes' masks of taught objects take their names
                from rg_core.grounding.teach import refresh

                try:
                    refresh(self._ensure_grounder())
                except Exception as exc:  # noqa: BLE001 - the next query re-applies them
                    self.log.warning("taught names not applied to the new keyframes yet: %s: %s", type(exc).__name__, exc)
            self._supervised_count = len(sset.by_keyframe)
            self._train_seconds, self._train_blocked = 0.0, ""
            self.log.info("supervision: %d keyframes, %s masks in %s multi-view objects (%.2f s)", self._supervised_count,
                          mv.get("masks", 0), mv.get("objects", 0), time.perf_counter() - t)
            return True

    def _train(self) -> bool:
        """One slice of field training under the stop test. The field answers from its first stop
        (converged, or train_seconds_max spent) and trains again when the supervision changes."""
        w = self.wcfg
        if self._train_blocked or self._supervised_count == 0:
            return False
        if w.train_seconds_max > 0 and self._train_seconds >= w.train_seconds_max:
            if self.field is not None and self.field.stop is None:
                self.field.stop = {"stopped": "seconds", "steps": self.field.steps,
                                   "seconds": round(self._train_seconds, 3)}
            return False
        with self.lock:
            if self.field is None:
                try:
                    from rg_core.field import FeatureField
                except ImportError as exc:
                    self._train_blocked = f"feature field not available: {exc}"
                    self.log.warning(self._train_blocked)
                    return False
                self.field = FeatureField(self.mapper, self.cfg.field)
            r = self.field.train(seconds=w.train_slice, converge=True, final=False, until=self.caller_waits)
        self._train_seconds += float(r.get("seconds", 0.0))
        if r.get("stop", {}).get("stopped") == "converged":
            if r["steps"]:
                self.log.info("%s", describe(r["stop"]))
            return r["steps"] > 0  # converged on this supervision: nothing to train until it changes
        if "skipped" in r:
            self._train_blocked = str(r["skipped"])
            self.log.info("field training waits: %s", self._train_blocked)
            return False
        return True

    def _refine(self) -> bool:
        n = self.wcfg.refine_iters
        if n <= 0 or not self.mapper.keyframes or self._refined_iters >= self.cfg.map.final_iters:
            return False
        with self.lock:   # slices of one converging refinement: it ends when a pass stops helping
            self.mapper.refine(n, resume=True)
        self._refined_iters += n
        if self.mapper.last_refine.get("stopped") == "converged":
            self._refined_iters = self.cfg.map.final_iters    # until the next keyframe
        return True

    # ------------------------------------------------------------------------------ perception

    def _load_perception(self) -> tuple[Any, Any]:
        from rg_core.perception.embed import make_embedder
        from rg_core.perception.masks import make_mask_generator

        return make_mask_generator(self.wcfg.mask_generator), make_embedder(self.wcfg.embedder)

    def _load_perception_thread(self) -> None:
        t = time.perf_counter()
        try:
            self._perception = self._perception_loader()
        except Exception as exc:  # noqa: BLE001 - mapping goes on without features
            self.perception_state = f"failed: {type(exc).__name__}: {exc}"
            self.log.error("perception models did not load (mapping goes on, no feature training): %s",
                           self.perception_state)
            return
        self.perception_state = "ready"
        self.log.info("perception models loaded in %.1f s (%s, %s)", time.perf_counter() - t,
                      self.wcfg.mask_generator, self.wcfg.embedder)
        self.queue.wake()
