"""Map snapshots (rg_core/map/snapshot.py): a snapshot answers as the map did when it was taken, however
the live map changes afterwards (frames, refinement, eviction, field training, teaching), shares
the live map's tensors instead of copying them, and keeps the query caches warm while nothing changed."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from rg_core.config import RGConfig
from rg_core.grounding.pipeline import Grounder
from rg_core.map.snapshot import snapshot_bytes, take_snapshot
from rg_core.map.store import load_map
from rg_core.perception.embed import MiniLMText


@pytest.fixture(scope="module")
def text():
    return MiniLMText()


@pytest.fixture
def live(minilm_map_file):
    return load_map(minilm_map_file)


def values(m) -> dict:
    """Every number a query reads from a map, copied."""
    out = {f"g.{k}": v.detach().clone() for k, v in m.gaussians.tensors().items()}
    out["latents"] = m.field.latents.clone()
    out.update({f"mlp.{k}": v.clone() for k, v in m.field.language_mlp.state_dict().items()})
    out.update({f"imlp.{k}": v.clone() for k, v in m.field.instance_mlp.state_dict().items()})
    out["keyframes"] = torch.tensor([kf.index for kf in m.keyframes])
    out["sup"] = torch.tensor(sorted(m.supervision.by_keyframe))
    return out


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(a[k].shape == b[k].shape and torch.equal(a[k], b[k]) for k in a)


def answer(m, text, query: str):
    g = Grounder.from_map(m, RGConfig(), field=m.field, text_encoder=text)
    r = g.ground(query)
    return r.success, sorted(int(i) for o in r.objects for i in o.gaussian_ids), round(float(r.confidence), 6)


def test_a_snapshot_does_not_change_while_the_map_does(live, synth_scene, text):
    name = synth_scene.objects[0].name
    before = answer(live, text, name)
    assert before[0] and before[1]
    snap = take_snapshot(live)
    frozen = values(snap)
    copied = live.field.latents.numel() * 4 + sum(   # the field and the supervision embeddings; no Gaussian
        p.numel() * 4 for mlp in (live.field.language_mlp, live.field.instance_mlp) for p in mlp.parameters())
    copied += sum(t.numel() * t.element_size() for s in live.supervision.by_keyframe.values()
                  for t in (s.embeddings, s.embeddings_view, s.model) if t is not None)
    assert snapshot_bytes(snap, live) == copied
    # the live map moves on: field training, refinement, a new frame, eviction, a new keyframe set
    live.field.train(iters=5)
    live.refine(3, converge=False)
    f = synth_scene.test[0]
    live.add_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, live.last_stamp + 1.0)
    kf = live.keyframes[0]
    live.evict(len(live.gaussians) // 4, kf.K, kf.cam_to_world, int(kf.rgb.shape[1]), int(kf.rgb.shape[0]))
    live.field.sync()
    k0 = next(iter(live.supervision.by_keyframe))
    live.supervision.by_keyframe[k0].embeddings[0] = 0.0   # what a supervision pass's multi-view means do
    frozen_emb = snap.supervision.by_keyframe[k0].embeddings
    assert float(frozen_emb[0].abs().sum()) > 0, "the snapshot shared an embedding the live map edits in place"
    assert not same(values(live), frozen)          # it did change
    assert same(values(snap), frozen)              # the snapshot did not
    assert answer(snap, text, name) == before      # and answers as the map did when it was taken


def test_a_snapshot_shares_tensors_and_reuses_what_did_not_change(live):
    s1 = take_snapshot(live)
    for k, t in live.gaussians.tensors().items():
        assert s1.gaussians.tensors()[k] is t      # shared, not copied
    s2 = take_snapshot(live, s1)
    assert s2.supervision is s1.supervision        # unchanged parts are the previous snapshot's own
    assert s2.field.latents is s1.field.latents and s2.field is not s1.field
    assert snapshot_bytes(s2, live) == snapshot_bytes(s1, live)
    live.field.train(iters=2)
    s3 = take_snapshot(live, s2)
    assert s3.field.latents is not s2.field.latents and torch.equal(s2.field.latents, s1.field.latents)
    live.refine(1, converge=False)                 # the optimiser makes new tensors: the snapshot keeps the old ones
    assert s3.gaussians.means is not live.gaussians.means
    k0, k1 = list(live.supervision.by_keyframe)[:2]
    live.supervision.by_keyframe[k0].embeddings[0] = 0.0   # an in-place edit is seen (torch's _version) ...
    s4 = take_snapshot(live, s3)
    assert s4.supervision is not s3.supervision
    assert float(s4.supervision.by_keyframe[k0].embeddings[0].abs().sum()) == 0.0
    assert float(s3.supervision.by_keyframe[k0].embeddings[0].abs().sum()) > 0.0
    assert s4.supervision.by_keyframe[k1] is s3.supervision.by_keyframe[k1]   # ... and only that record is copied


def test_query_caches_stay_warm_across_unchanged_snapshots(live, synth_scene, text):
    name = synth_scene.objects[1].name
    s1 = take_snapshot(live)
    g = Grounder.from_map(s1, RGConfig(), field=s1.field, text_encoder=text)
    first = g.ground(name)
    misses = g.cache.misses
    s2 = take_snapshot(live, s1)                   # nothing changed in between
    g.mapper, g.field = s2, s2.field
    again = g.ground(name)
    assert g.cache.misses == misses and g.cache.hits > 0, "an unchanged snapshot emptied the caches"
    assert [o.gaussian_ids.tolist() for o in again.objects] == [o.gaussian_ids.tolist() for o in first.objects]
    live.field.train(iters=2)                      # a changed field: the caches follow the new snapshot
    s3 = take_snapshot(live, s2)
    g.mapper, g.field = s3, s3.field
    inv = g.cache.invalidations
    g.ground(name)
    assert g.cache.invalidations == inv + 1


def test_a_frozen_field_is_never_trained_or_synced(live):
    snap = take_snapshot(live)
    n = len(snap.field.latents)
    assert snap.field.sync() == 0 and len(snap.field.latents) == n
    assert snap.optim is None and snap.field._m is None
    assert np.isclose(float(snap.field.latents.sum()), float(live.field.latents.sum()))
