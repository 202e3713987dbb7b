"""The field's stop test (rg_core.field.converge): training stops once its accuracy on held-out
pixels stops improving, at the same step for the same seed, never trains on those pixels, restarts when the
supervision changes, and the decision is saved with the map."""
import pytest
import torch

from rg_core.config import FieldConfig, MapConfig
from rg_core.field import FeatureField
from rg_core.field.converge import Convergence, describe, holdout_pixels
from rg_core.field.oracle import RandomNameEmbedding, oracle_supervision
from rg_core.map.mapper import Mapper
from rg_core.map.run import stream_frames

CEILING = 1500  # steps: the tests never depend on wall-clock time


@pytest.fixture(scope="module")
def small_map(synth_scene):
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    mapper = Mapper(MapConfig(width=80, iters_per_keyframe=2, final_iters=0, seed_stride=4))
    stream_frames(mapper, synth_scene.train[:4], progress=False)
    oracle_supervision(mapper, synth_scene.train, synth_scene.objects, RandomNameEmbedding(dim=96, seed=0))
    yield mapper
    torch.set_num_threads(n)


def _field(mapper, **kw):
    return FeatureField(mapper, FieldConfig(rays_per_step=64, check_every=5, converge_window=20, converge_min_steps=20,
                                            **kw))


def test_stops_on_convergence_at_the_same_step_for_the_same_seed(small_map):
    a, b = _field(small_map), _field(small_map)
    ra, rb = a.train(iters=CEILING, converge=True), b.train(iters=CEILING, converge=True)
    assert ra["stop"]["stopped"] == "converged", ra["stop"]
    assert 20 <= ra["steps"] < CEILING and ra["steps"] % 5 == 0
    assert ra["steps"] == rb["steps"] and torch.equal(a.latents, b.latents)
    curve = ra["curve"]  # (steps, seconds, accuracy, loss, language accuracy, instance accuracy)
    assert len(curve) == ra["steps"] // 5 + 1 and curve[0][0] == 0
    assert max(h[2] for h in curve) > curve[0][2] + 0.1 and min(h[3] for h in curve) < curve[0][3]
    # The rule itself: the best accuracy of the last window is within tol of the best before it.
    n = curve[-1][0]
    assert max(h[2] for h in curve) - max(h[2] for h in curve if h[0] <= n - 20) < 0.005
    assert describe(ra["stop"]).startswith(f"field: converged at ") and f"{ra['steps']} steps" in describe(ra["stop"])
    # Converged on unchanged supervision: another call has nothing to do.
    again = a.train(iters=50, converge=True)
    assert again["steps"] == 0 and again["stop"] == ra["stop"]


def test_a_fixed_budget_runs_whole(small_map):
    f = _field(small_map)
    r = f.train(iters=60)  # an explicit budget without converge=True: no stop test
    assert r["steps"] == 60 and r["stop"]["stopped"] == "steps" and f.convergence is None
    f0 = _field(small_map, converge_tol=0.0)  # the test off: the whole budget
    assert f0.train(iters=60, converge=True)["steps"] == 60


def test_heldout_pixels_are_never_trained_on(small_map, monkeypatch):
    f = _field(small_map, holdout=0.2)
    kf = f._supervised()[0]
    *_, weights, held = f._train_view(kf)
    assert 0.1 < float(held.float().mean()) < 0.3 and bool((weights > 0).all())
    assert torch.equal(held, holdout_pixels(len(held), 0.2, f.cfg.seed, kf.index))  # fixed per seed and view
    assert not bool(_field(small_map, holdout=0.0)._train_view(kf)[-1].any())
    drawn = []  # a spy on the ray draw: every pixel a step trains on lies outside its view's held-out set
    real = torch.multinomial
    monkeypatch.setattr(torch, "multinomial", lambda *a, **k: drawn.append(real(*a, **k)) or drawn[-1])
    for _ in range(20):
        r = f.train_step()
        view = next(k for k in f._supervised() if k.index == r["keyframe"])
        assert len(drawn[-1]) == 64 and not bool(f._train_view(view)[-1][drawn[-1]].any())


def test_new_supervision_restarts_the_test(small_map, synth_scene):
    f = _field(small_map)
    assert f.train(iters=CEILING, converge=True)["stop"]["stopped"] == "converged"
    old = f.convergence
    oracle_supervision(small_map, synth_scene.train, synth_scene.objects, RandomNameEmbedding(dim=96, seed=1))
    r = f.train(iters=10, converge=True)
    assert r["steps"] == 10 and f.convergence is not old and f.convergence.decision is None


def test_rule_edge_cases():
    c = Convergence()
    assert not c.converged(0.005, 50)  # no measurement yet
    c.history = [(0, 0.0, 0.5), (10, 0.1, 0.8)]
    assert not c.converged(0.005, 50)  # fewer steps than the window
    c.history += [(50, 0.5, 0.9), (60, 0.6, 0.95)]
    assert not c.converged(0.005, 50)  # 0.8 -> 0.95 over the last 50 steps
    c.history += [(100, 1.0, 0.951), (110, 1.1, 0.953)]
    assert c.converged(0.005, 50)  # 0.95 -> 0.953: < 0.5 points
    assert not c.converged(0.001, 50)  # but not < 0.1 points
    c.history += [(120, 1.2, float("nan")), (170, 1.7, 0.9)]
    assert c.converged(0.005, 50)  # a worse or non-finite measurement is never the best
