"""Feature field: oracle-supervised accuracy, loss gradients, incremental training, persistence,
stability. One small synthetic scene (conftest), one map, one trained field per module."""
import dataclasses

import numpy as np
import pytest
import torch

from rg_core.config import FieldConfig, MapConfig
from rg_core.field import (
    FeatureField,
    QuantileScale,
    ScaleMLP,
    instance_loss,
    language_loss,
    language_targets,
    shares_group,
)
from rg_core.field.oracle import RandomNameEmbedding, oracle_checks, oracle_supervision
from rg_core.map.mapper import Mapper
from rg_core.map.run import stream_frames
from rg_core.map.store import MapFileError, load_map, save_map
from rg_core.perception.pca import PCA
from rg_core.perception.supervision import KeyframeSupervision, SupervisionSet

EMBED = RandomNameEmbedding(dim=96, seed=0)
TRAIN_ITERS = 200


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """2 shared cores: one intra-op thread is several times faster for these small tensors."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def make_map(scene, frames=None, seed_stride: int = 4) -> Mapper:
    mapper = Mapper(MapConfig(width=160, iters_per_keyframe=5, final_iters=0, seed_stride=seed_stride))
    stream_frames(mapper, scene.train if frames is None else frames, progress=False)
    return mapper


@pytest.fixture(scope="module")
def trained(oracle_field):
    """The session's oracle field (conftest: stride-2 map at 160 px, ground-truth masks, 200 steps)."""
    field, embed = oracle_field
    assert field.steps == TRAIN_ITERS and embed.dim == EMBED.dim
    return field


def test_oracle_relevancy_and_instance_separation(trained, synth_scene):
    """Each object's name peaks inside it and its pixels sit nearest their own instance. Over the 16
    views (78 object-view pairs; 10 of them in the 2 held-out views) after 200 steps: measured,
    2026-12-01, over torch's default / AVX2 / AVX-512 kernels, OpenBLAS Sandybridge / Haswell /
    SkylakeX and one or two threads: argmax in mask 0.88-0.96 over all views, 0.8-0.9 held out;
    instance separation 0.989-0.995. One held-out pair is 0.1, so the held-out bar leaves one
    pair's rounding (and at 400 steps held-out argmax fell to 0.5-0.9 on every variant: training
    longer does not steady it)."""
    held = oracle_checks(trained, synth_scene.test, synth_scene.objects, EMBED)
    every = oracle_checks(trained, [*synth_scene.train, *synth_scene.test], synth_scene.objects, EMBED)
    assert held["pairs"] >= 6 and every["pairs"] >= 60, (held, every)
    assert every["argmax_in_mask"] >= 0.85, every
    assert held["argmax_in_mask"] >= 0.7, held
    assert held["instance_separation"] >= 0.98 and every["instance_separation"] >= 0.98, (held, every)


def test_render_is_one_call_with_colour(trained):
    kf = trained.mapper.keyframes[-1]
    w, h = kf.size
    r = trained.render(kf.K, kf.cam_to_world, w, h)
    assert r.latent.shape == (h, w, 32) and r.rgb.shape == (h, w, 3) and r.depth.shape == (h, w)
    ref = trained.mapper.render(kf.K, kf.cam_to_world, w, h)
    torch.testing.assert_close(r.rgb, ref.channels, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(r.alpha, ref.alpha, atol=1e-6, rtol=1e-6)
    lang, inst = trained.language(r.latent, 0.05), trained.instance(r.latent, 0.05)
    assert lang.shape == (h, w, 64) and inst.shape == (h, w, 16)
    torch.testing.assert_close(inst.norm(dim=-1), torch.ones(h, w))
    g = trained.gaussian_instance(0.05)
    assert g.shape == (len(trained.mapper.gaussians), 16) and torch.isfinite(g).all()


# ------------------------------------------------------------------------------------ losses

def test_language_loss_gradcheck():
    pred = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
    target = torch.randn(5, 4, dtype=torch.float64)
    target[0] = pred.detach()[0] + 0.01  # inside the quadratic zone of the Huber loss too
    assert torch.autograd.gradcheck(lambda p: language_loss(p, target, 0.1), (pred,))
    mlp = ScaleMLP(3, 4, hidden=5, frequencies=2).double()
    lat = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    u = torch.rand(5, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: language_loss(mlp(x, u), target, 0.1), (lat,))


def test_instance_loss_gradcheck():
    torch.manual_seed(0)
    feat = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    share = torch.rand(6, 6) > 0.5
    share = share | share.T
    assert torch.autograd.gradcheck(lambda f: instance_loss(f, share, 1.0), (feat,))
    assert torch.autograd.gradcheck(lambda f: instance_loss(f, share, 10.0), (feat,))  # all hinges active
    mlp = ScaleMLP(3, 4, hidden=5, frequencies=2, unit=True).double()
    assert torch.autograd.gradcheck(lambda f: instance_loss(mlp(f, 0.3), share, 1.0), (feat,))


def test_instance_loss_pulls_and_pushes():
    f = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 0.0]])
    share = torch.tensor([[1, 1, 0], [1, 1, 0], [0, 0, 1]], dtype=torch.bool)
    # pair (0,1) shares: distance 3; pairs (0,2) at 0 and (1,2) at 3 do not: hinge 1 and 0.
    assert float(instance_loss(f, share, 1.0)) == pytest.approx(3.0 + 0.5, abs=1e-5)


def test_groups_and_targets_follow_the_definition():
    g = torch.Generator().manual_seed(1)
    members = torch.rand(30, 6, generator=g) > 0.6
    scales = torch.tensor([0.02, 0.05, 0.07, 0.1, 0.3, 1.0])
    targets = torch.randn(6, 4, generator=g)
    for s in (0.0, 0.02, 0.06, 0.25, 5.0):
        share = shares_group(members, scales, s)
        tgt = language_targets(members, scales, targets, s)
        for i in range(30):
            for j in range(30):
                brute = any(bool(members[i, m] and members[j, m]) and float(scales[m]) <= s for m in range(6))
                assert bool(share[i, j]) == brute
            ms = [m for m in range(6) if members[i, m] and float(scales[m]) <= s]
            want = targets[max(ms, key=lambda m: float(scales[m]))] if ms else torch.zeros(4)
            torch.testing.assert_close(tgt[i], want)


# ------------------------------------------------------------------------------------ incremental

def visible_rows(field, kf) -> torch.Tensor:
    """Gaussians that contribute to a keyframe's training render (non-zero gradient of the image)."""
    g = field.mapper.gaussians
    w, h = kf.size
    tw = min(field.cfg.train_width, w)
    th = max(1, int(round(h * tw / w)))
    from rg_core.geometry.conventions import scale_intrinsics
    from rg_core.render import rasterize

    ones = torch.ones(len(g), 1, requires_grad=True)
    out = rasterize(g.means, g.scales, g.quats, g.opacities, ones,
                    field.mapper.camera(scale_intrinsics(kf.K, tw / w, th / h), kf.cam_to_world, tw, th))
    out.channels.sum().backward()
    return ones.grad[:, 0] != 0


def test_latents_outside_the_window_do_not_drift(trained):
    f = FeatureField(trained.mapper, dataclasses.replace(trained.cfg, window=1, revisit=0.0))
    f.latents = trained.latents.clone()
    f.train(iters=3)  # Adam moments everywhere in the last view
    last = f._supervised()[-1]
    seen = visible_rows(f, last)
    assert 0 < int(seen.sum()) < len(seen)
    before = f.latents.clone()
    for _ in range(3):
        assert f.train_step()["keyframe"] == last.index
    assert torch.equal(f.latents[~seen], before[~seen])  # bitwise
    assert not torch.equal(f.latents[seen], before[seen])
    trained.mapper.field = trained


def test_new_gaussians_start_from_neighbours_and_pruning_keeps_rows(synth_scene):
    mapper = make_map(synth_scene, synth_scene.train[:3])
    f = FeatureField(mapper, FieldConfig(init_neighbours=3))
    g = mapper.gaussians
    old_means, old_lat = g.means.clone(), f.latents.clone()
    new = old_means[:4] + 0.0005
    g.append(new, torch.full((4,), 0.003), torch.rand(4, 3), 0.9)
    mapper.optim.sync()
    assert f.sync() == 4
    d = torch.cdist(new.double(), old_means.double())
    want = old_lat[d.topk(3, largest=False).indices].mean(1)
    torch.testing.assert_close(f.latents[-4:], want)
    assert f.latents[-4:].abs().sum() > 0
    assert torch.equal(f.latents[:-4], old_lat)
    # A second append writes into the room the first one left: old rows are neither copied nor changed,
    # and the field's revision (what per-row caches of old rows are keyed by) stays.
    rev, ptr, lat = f.revision, f.latents.data_ptr(), f.latents.clone()
    far = old_means[4:6] + torch.tensor([5.0, 0.0, 0.0])                    # no old Gaussian within reach
    g.append(far, torch.full((2,), 0.003), torch.rand(2, 3), 0.9)
    mapper.optim.sync()
    assert f.sync() == 2 and f.revision == rev and f.latents.data_ptr() == ptr
    assert torch.equal(f.latents[:-2], lat) and len(f._m) == len(f._v) == len(f._t) == len(g)
    d = torch.cdist(far.double(), g.means.detach()[:-2].double())
    torch.testing.assert_close(f.latents[-2:], lat[d.topk(3, largest=False).indices].mean(1))
    old_lat = lat
    # Pruning shifts rows; the field re-associates by centre (as the mapper reports prunes).
    lat = f.latents.clone()
    keep = torch.ones(len(g), dtype=torch.bool)
    keep[::3] = False
    g.keep(keep)
    mapper.optim.keep(keep)
    mapper.totals["pruned"] += int((~keep).sum())
    rev = f.revision
    f.sync()
    assert f.latents.shape == (len(g), 32) and torch.equal(f.latents, lat[keep])
    assert f.revision == rev + 1
    # Eviction at the map's bound (Mapper.evict) is followed the same way.
    lat, means = f.latents.clone(), g.means.detach().clone()
    kf = mapper.keyframes[0]
    n = mapper.evict(len(g) // 4, kf.K, kf.cam_to_world, *kf.size)
    assert n > 0
    f.sync()
    idx = torch.cdist(g.means.detach().double(), means.double()).argmin(1)
    assert f.latents.shape == (len(g), 32) and torch.equal(f.latents, lat[idx])


def test_training_follows_a_growing_map_and_pca_refits(synth_scene):
    frames = synth_scene.train
    mapper = make_map(synth_scene, frames[:5])
    oracle_supervision(mapper, frames, synth_scene.objects, EMBED)
    f = FeatureField(mapper, FieldConfig(rays_per_step=64))
    assert f.train(iters=3)["steps"] == 3
    n0 = len(mapper.gaussians)
    stream_frames(mapper, frames[5:], progress=False)
    sset = mapper.supervision
    fresh = oracle_supervision(mapper, frames, synth_scene.objects, EMBED)  # new keyframes, new PCA
    mapper.supervision = sset
    for k, s in fresh.by_keyframe.items():
        if k not in sset.by_keyframe:
            sset.add(k, s)
    assert len(mapper.gaussians) != n0
    stats = f.train(iters=3)
    assert stats["steps"] == 3 and np.isfinite(stats["loss"])
    assert f.latents.shape == (len(mapper.gaussians), 32) and torch.isfinite(f.latents).all()
    # A keyframe dropped at the map's keyframe budget leaves the field's per-keyframe caches.
    dropped = mapper.drop_redundant_keyframe()
    assert dropped is not None and dropped.index not in sset.by_keyframe
    assert f.train(iters=2)["steps"] == 2 and set(f._masks) <= {kf.index for kf in mapper.keyframes}
    # A PCA refit re-expresses the language mapper: new output = old output, decompressed and
    # compressed again in the new basis.
    lat = torch.randn(10, 32)
    before = sset.pca.pca.inverse(f.language(lat, 0.05))
    sset.pca.pca = PCA.fit(torch.cat(sset.pca.raw + [EMBED(["a name never seen"])]), 64)
    sset.pca.version += 1
    f._refresh_supervision()
    torch.testing.assert_close(f.language(lat, 0.05), sset.pca.pca.transform(before), atol=1e-4, rtol=1e-4)


# ------------------------------------------------------------------------------------ persistence

def test_until_ends_training_before_the_next_step(synth_scene):
    """The node's slices pass until=caller_waits: a service call waits for one step, not a slice.
    An interrupted call is no stop decision, even with final=True."""
    mapper = make_map(synth_scene, synth_scene.train[:3])
    oracle_supervision(mapper, synth_scene.train, synth_scene.objects, EMBED)
    f = FeatureField(mapper, FieldConfig(rays_per_step=64))
    asked = []
    r = f.train(iters=10, until=lambda: asked.append(1) or len(asked) > 2)
    assert r["steps"] == 2 and f.steps == 2 and len(asked) == 3
    assert r["stop"]["stopped"] == "interrupted" and f.stop is None
    r = f.train(seconds=60.0, converge=True, final=False, until=lambda: True)
    assert r["steps"] == 0 and f.steps == 2 and r["stop"]["stopped"] == "interrupted"


def test_field_saved_with_the_map(trained, tmp_path):
    path = save_map(trained.mapper, tmp_path / "m.rgmap")
    back = load_map(path)
    assert back.field is not None and torch.equal(back.field.latents, trained.latents)
    kf = back.keyframes[0]
    w, h = kf.size
    a = trained.render(kf.K, kf.cam_to_world, w, h).latent
    b = back.field.render(kf.K, kf.cam_to_world, w, h).latent
    torch.testing.assert_close(trained.language(a, 0.04), back.field.language(b, 0.04))
    torch.testing.assert_close(trained.normalise_scale(torch.tensor([0.01, 0.1])),
                               back.field.normalise_scale(torch.tensor([0.01, 0.1])))
    # A version-1 file (before the field existed) still loads, with no field.
    data = torch.load(path, weights_only=True)
    data["version"] = 1
    del data["field"]
    torch.save(data, tmp_path / "v1.rgmap")
    assert load_map(tmp_path / "v1.rgmap").field is None
    data["version"] = 2
    data["field"] = trained.state_dict()
    data["field"]["latents"] = data["field"]["latents"][:-1]
    torch.save(data, tmp_path / "bad.rgmap")
    with pytest.raises(MapFileError, match="feature field"):
        load_map(tmp_path / "bad.rgmap")
    trained.mapper.field = trained


# ------------------------------------------------------------------------------------ stability

def test_scale_transform_extremes():
    q = QuantileScale.fit(torch.tensor([0.02, 0.05, 0.05, 0.05, 0.3]), 9)
    s = torch.tensor([0.0, 1e-9, 0.02, 0.05, 0.3, 1e6, float("nan"), float("inf")])
    u = q(s)
    assert torch.isfinite(u).all() and (u >= 0).all() and (u <= 1).all()
    assert u[0] == 0 and u[5] == 1
    xs = torch.logspace(-4, 2, 200)
    assert (q(xs)[1:] >= q(xs)[:-1]).all()  # monotone
    assert torch.isfinite(QuantileScale.fit(torch.tensor([0.1]), 5)(xs)).all()  # one scale
    with pytest.raises(ValueError, match="no finite scales"):
        QuantileScale.fit(torch.tensor([]))


def test_empty_and_degenerate_supervision(synth_scene):
    empty = FeatureField(Mapper(MapConfig(width=160)))
    assert empty.latents.shape == (0, 32)
    assert "skipped" in empty.train_step() and empty.train(iters=5)["steps"] == 0
    with pytest.raises(RuntimeError, match="no scale transform"):
        empty.normalise_scale(0.1)
    mapper = make_map(synth_scene, synth_scene.train[:2])
    f = FeatureField(mapper)
    assert "no keyframe has supervision" in f.train_step()["skipped"]
    # One-pixel masks, a zero scale and a huge one: training runs and nothing becomes NaN.
    sset = SupervisionSet()
    rng = np.random.default_rng(0)
    for kf in mapper.keyframes:
        w, h = kf.size
        M = 6
        masks = np.zeros((M, h, w), bool)
        for i in range(M):
            masks[i, rng.integers(h), rng.integers(w)] = True
        masks[-1] = True  # the whole view
        sset.add(kf.index, KeyframeSupervision(masks, np.ones(M, np.float32), np.ones(M, np.int8),
                                               np.array([0.0, 1e-7, 0.01, 0.05, 1e6, 0.2], np.float32),
                                               EMBED([f"n{i}" for i in range(M)])))
    mapper.supervision = sset
    stats = f.train(iters=4)
    assert stats["steps"] == 4 and np.isfinite(stats["loss"])
    assert torch.isfinite(f.latents).all()
    for p in list(f.language_mlp.parameters()) + list(f.instance_mlp.parameters()):
        assert torch.isfinite(p).all()
    for s in (0.0, 1e6, float("nan")):
        assert torch.isfinite(f.language(f.latents[:5], s)).all() and torch.isfinite(f.instance(f.latents[:5], s)).all()
    with pytest.raises(ValueError, match="latent"):
        f.language(torch.zeros(3, 7), 0.1)
