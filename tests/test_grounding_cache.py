"""Map caches of the Grounder (clusters per scale and region, field renders per keyframe, spacing,
vocabulary): a cached Grounder answers exactly as one that recomputes everything, and a change of
the map (idle refinement: same Gaussians and frames) or of the field empties the caches."""
import re

import numpy as np
import pytest
import torch

from rg_core.config import RGConfig
from rg_core.grounding.pipeline import Grounder
from rg_core.map.store import load_map, save_map


def same(a, b):
    assert a.success == b.success and a.target == b.target and a.message == b.message
    assert a.reference_view == b.reference_view and a.scale == b.scale and a.explanation == b.explanation
    assert len(a.objects) == len(b.objects)
    for x, y in zip(a.objects, b.objects):
        np.testing.assert_array_equal(x.gaussian_ids, y.gaussian_ids)
        np.testing.assert_array_equal(x.aabb_min, y.aabb_min)
        np.testing.assert_array_equal(x.obb_extent, y.obb_extent)


@pytest.fixture()
def own_map(oracle_field, tmp_path):
    """A private copy of the session map and field (this test changes them)."""
    field, embed = oracle_field
    m = load_map(save_map(field.mapper, tmp_path / "m.rgmap"))
    field.mapper.field = field
    return m, embed


def grounders(m, embed, names):
    from rg_core.perception.reasoning import TextReasoner

    r = TextReasoner()
    return [Grounder(m, m.field, RGConfig(), reasoner=r, text_encoder=embed, scene_names=names, cache=c)
            for c in (True, False)]


def test_cached_answers_equal_uncached(own_map, synth_scene):
    m, embed = own_map
    names = [o.name for o in synth_scene.objects]
    cached, plain = grounders(m, embed, names)
    for round_ in range(2):
        for n in names:
            before = cached.cache.misses
            a, b = cached.ground(n, mode="explicit"), plain.ground(n, mode="explicit")
            same(a, b)
            if round_ == 1 and a.success:
                assert cached.cache.misses == before, "second round: every map-only result from the cache"
    assert cached.cache.hits > 0 and plain.cache.hits == 0
    # The relevancy peak (computed over the reference mask's box only) is the peak over the whole view.
    r = cached.ground(names[0], mode="explicit")
    kf = next(k for k in m.keyframes if k.index == r.reference_view)
    w, h = kf.size
    rel, fr = cached.relevancy_view(r.target, r.scale, kf.K, kf.cam_to_world, w, h)
    smooth = torch.nn.functional.avg_pool2d(rel[None, None], 3, 1, 1, count_include_pad=False)[0, 0]
    px, py = (int(v) for v in re.search(r"most relevant pixel \((\d+), (\d+)", r.explanation).groups())
    masks = m.supervision.by_keyframe[kf.index].masks
    inside = [i for i in range(len(masks)) if masks[i][py, px]]
    assert inside, "the peak lies in a mask of the reference view"
    best = max(float(torch.where(torch.from_numpy(masks[i]), smooth, torch.full_like(smooth, -1.0)).max()) for i in inside)
    assert float(smooth[py, px]) == pytest.approx(best, abs=1e-6)


def test_map_and_field_changes_invalidate(own_map, synth_scene):
    m, embed = own_map
    names = [o.name for o in synth_scene.objects]
    cached, plain = grounders(m, embed, names)
    cached.ground(names[0], mode="explicit")
    s0, n0, f0 = cached.spacing(), len(m.gaussians), m.frames_seen
    # Idle refinement: the same Gaussians and frames, moved (none pruned: a count cannot tell).
    prune = m.cfg.prune_opacity, m.cfg.prune_scale
    m.cfg.prune_opacity, m.cfg.prune_scale = 0.0, float("inf")
    m.refine(3)
    m.cfg.prune_opacity, m.cfg.prune_scale = prune
    assert len(m.gaussians) == n0 and m.frames_seen == f0
    inv = cached.cache.invalidations
    same(cached.ground(names[1], mode="explicit"), plain.ground(names[1], mode="explicit"))
    assert cached.cache.invalidations == inv + 1
    assert cached.spacing() == plain.spacing() and cached.spacing() != s0
    # An in-place edit of the Gaussians (no new tensor) is seen too.
    with torch.no_grad():
        m.gaussians.means.add_(0.001)
    same(cached.ground(names[1], mode="explicit"), plain.ground(names[1], mode="explicit"))
    assert cached.cache.invalidations == inv + 2
    # Training the field.
    m.field.train(iters=3)
    same(cached.ground(names[0], mode="explicit"), plain.ground(names[0], mode="explicit"))
    assert cached.cache.invalidations == inv + 3
    # Nothing changed: no invalidation.
    cached.ground(names[0], mode="explicit")
    assert cached.cache.invalidations == inv + 3
    # A frame the map already explains changes nothing a query reads: the caches stay; a keyframe does not.
    explained = 0
    for f in synth_scene.train:
        before = cached.cache.invalidations
        r = m.add_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, f.stamp + 1000.0)
        same(cached.ground(names[0], mode="explicit"), plain.ground(names[0], mode="explicit"))
        assert cached.cache.invalidations == before + int(r.keyframe), r.reason
        explained += not r.keyframe
    assert explained > 0


def test_growth_elsewhere_keeps_vocabulary_and_the_clusters_asked(own_map, synth_scene):
    """Gaussians appended far from every object (a new part of the room): the vocabulary and the
    clusters of a region already asked stay (the same objects, not recomputed), the answers equal an
    uncached Grounder's; training the field empties the clusters, refinement the map's tables."""
    m, embed = own_map
    names = [o.name for o in synth_scene.objects]
    cached, plain = grounders(m, embed, names)
    g = m.gaussians

    def grow(n: int, dx: float) -> None:
        sel = torch.arange(n) % len(g)
        g.append(g.means.detach()[sel] + torch.tensor([dx, 0.0, 0.0]), g.scales.detach()[sel],
                 g.colors.detach()[sel], 0.9)
        m.optim.sync()

    grow(len(g) // 4, 6.0)                        # far enough for the query's region to leave it out
    same(cached.ground(names[0], mode="explicit"), plain.ground(names[0], mode="explicit"))
    clusters, vocab = dict(cached.cache.tables["clusters"]), dict(cached.cache.tables["vocabulary"])
    groups = dict(cached.cache.tables["groups"])
    assert clusters and vocab and groups
    for gr in groups.values():   # a region's groups hold rows for its Gaussians only, none map-sized
        assert gr.ids is not None and len(gr.labels) == len(gr.ids) == len(gr.features) < len(g)
    rev = m.field.revision
    grow(50, 9.0)
    same(cached.ground(names[0], mode="explicit"), plain.ground(names[0], mode="explicit"))
    assert m.field.revision == rev
    assert not any(cached.cache.tables["groups"].get(k) is v for k, v in groups.items())   # the map's: made anew
    assert all(cached.cache.tables["clusters"].get(k) is v for k, v in clusters.items())
    assert all(cached.cache.tables["vocabulary"].get(k) is v for k, v in vocab.items())
    m.field.train(iters=2)
    same(cached.ground(names[0], mode="explicit"), plain.ground(names[0], mode="explicit"))
    assert not any(cached.cache.tables["clusters"].get(k) is v for k, v in clusters.items())
    assert all(cached.cache.tables["vocabulary"].get(k) is v for k, v in vocab.items())


def test_an_answer_asked_again_is_kept_until_the_map_or_config_changes(own_map, synth_scene):
    m, embed = own_map
    names = [o.name for o in synth_scene.objects]
    cached, plain = grounders(m, embed, names)
    first = cached.ground(names[0], mode="explicit")
    assert "cached" not in first.timings
    misses = cached.cache.misses
    again = cached.ground(names[0], mode="explicit")
    same(again, first)
    assert "cached" in again.timings and cached.cache.misses == misses   # a lookup, nothing computed
    assert all(a is b for a, b in zip(again.objects, first.objects))   # the same objects (the scene graph's too)
    again.objects.clear()   # what a caller does with its answer stays its own
    again.target = "edited"
    same(cached.ground(names[0], mode="explicit"), first)
    # Another mode, result count or camera is another question.
    assert "cached" not in cached.ground(names[0], mode="explicit", max_results=2).timings
    cam = np.asarray(m.keyframes[0].cam_to_world, np.float64)
    assert "cached" not in cached.ground(names[0], mode="explicit", cam_to_world=cam).timings
    assert "cached" in cached.ground(names[0], mode="explicit", cam_to_world=cam).timings
    # A config change is seen: the answer is computed again, as an uncached Grounder's.
    cached.gcfg.min_confidence = plain.gcfg.min_confidence = 1.01
    r = cached.ground(names[0], mode="explicit")
    assert "cached" not in r.timings and not r.success
    same(r, plain.ground(names[0], mode="explicit"))
    # And so is a change of the map.
    with torch.no_grad():
        m.gaussians.means.add_(0.001)
    assert "cached" not in cached.ground(names[0], mode="explicit").timings


def test_mask_points_are_kept_with_the_supervision(own_map, synth_scene):
    from rg_core.grounding.stages import mask_points

    m, embed = own_map
    cached, plain = grounders(m, embed, [o.name for o in synth_scene.objects])
    kf = m.keyframes[0]
    want = mask_points(kf, m.supervision.by_keyframe[kf.index].masks[0], 150)
    got = cached.mask_points(kf, 0, 150)
    np.testing.assert_array_equal(got, want)
    assert cached.mask_points(kf, 0, 150) is got and plain.mask_points(kf, 0, 150) is not plain.mask_points(kf, 0, 150)
    np.testing.assert_array_equal(plain.mask_points(kf, 0, 150), want)
