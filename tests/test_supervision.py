"""Per-keyframe supervision: computed once, stored with the map, PCA across keyframes."""
import numpy as np
import pytest
import torch

from rg_core.config import MapConfig
from rg_core.map.mapper import Mapper
from rg_core.map.run import stream_frames
from rg_core.map.store import load_map, save_map
from rg_core.perception.masks import make_mask_generator
from rg_core.perception.supervision import build_supervision, supervise_map


@pytest.fixture(scope="module")
def supervised(synth_scene, conse_embedder):
    mapper = Mapper(MapConfig(width=160, iters_per_keyframe=3))
    stream_frames(mapper, synth_scene.train[:6], progress=False)
    sset = supervise_map(mapper, make_mask_generator("rgbd"), conse_embedder)
    return mapper, sset


def test_every_keyframe_gets_masks_scales_embeddings(supervised):
    mapper, sset = supervised
    assert set(sset.by_keyframe) == {kf.index for kf in mapper.keyframes}
    for kf in mapper.keyframes:
        s = sset.by_keyframe[kf.index]
        M = len(s.scales)
        assert M > 0 and s.masks.shape == (M, kf.size[1], kf.size[0]) and s.embeddings.shape == (M, 384)
        assert np.all(np.isfinite(s.scales)) and np.all(s.scales > 0) and np.all(s.scales < 5.0)
        assert set(s.seconds) == {"masks", "scales", "embed"}
    st = sset.stats()
    assert st["keyframes"] == len(mapper.keyframes) and st["masks_per_keyframe"] > 1
    assert st["pca"]["dim"] == 64 and 0.5 < st["pca"]["explained_variance"] <= 1.0 + 1e-6
    z = sset.compressed(mapper.keyframes[0].index)
    assert z.shape == (len(sset.by_keyframe[mapper.keyframes[0].index].scales), 64)


def test_computed_once_per_keyframe(supervised, conse_embedder):
    mapper, sset = supervised
    before = {k: id(v) for k, v in sset.by_keyframe.items()}
    again = supervise_map(mapper, make_mask_generator("rgbd"), conse_embedder)
    assert again is sset and {k: id(v) for k, v in again.by_keyframe.items()} == before


def test_supervision_saved_with_the_map(supervised, tmp_path):
    mapper, sset = supervised
    back = load_map(save_map(mapper, tmp_path / "m.rgmap"))
    assert back.supervision is not None and set(back.supervision.by_keyframe) == set(sset.by_keyframe)
    for k, s in sset.by_keyframe.items():
        b = back.supervision.by_keyframe[k]
        assert np.array_equal(b.masks, s.masks) and np.allclose(b.scales, s.scales)
        torch.testing.assert_close(b.embeddings, s.embeddings)
    k0 = next(iter(sset.by_keyframe))
    torch.testing.assert_close(back.supervision.compressed(k0), sset.compressed(k0))


def test_bad_inputs(conse_embedder):
    with pytest.raises(ValueError, match="differ in size"):
        build_supervision(np.zeros((10, 12, 3), np.uint8), np.ones((10, 10), np.float32), np.eye(3),
                          make_mask_generator("rgbd"), conse_embedder)


def test_each_object_embedded_in_at_most_k_views(synth_scene, conse_embedder, tmp_path):
    """views_per_object: masks and scales for every keyframe, embeddings only for each object's k
    largest views; every other mask takes its object's mean. The result survives save/load and a
    second call embeds nothing new."""
    from rg_core.perception.multiview import associate
    from rg_core.perception.supervision import supervise_map_multiview

    mapper = Mapper(MapConfig(width=160, iters_per_keyframe=3))
    stream_frames(mapper, synth_scene.train[:6], progress=False)
    sset, st = supervise_map_multiview(mapper, make_mask_generator("rgbd"), conse_embedder, views_per_object=2)
    keys, labels = associate(mapper, sset)
    own = np.array([bool(sset.by_keyframe[k].owned()[m]) for k, m in keys])
    per_object = np.bincount(labels, weights=own.astype(float))
    assert per_object.max() <= 2 and per_object.min() >= 1  # every object has its own embedding, at most 2
    assert st["masks_embedded"] == own.sum() < st["masks_total"] == len(keys)  # some masks were left out
    for lab in np.unique(labels):  # one embedding per object: the mean of its own views
        rows = [sset.by_keyframe[k].embeddings[m] for (k, m), l in zip(keys, labels) if l == lab]
        for r in rows[1:]:
            torch.testing.assert_close(r, rows[0])
    for s in sset.by_keyframe.values():
        torch.testing.assert_close(s.embeddings.norm(dim=-1), torch.ones(len(s.scales)))
    assert sset.pca.pca is not None and sset.pca.pca.n_fit == len(keys)
    again, st2 = supervise_map_multiview(mapper, make_mask_generator("rgbd"), conse_embedder, views_per_object=2)
    assert again is sset and st2["embedded_now"] == 0
    back = load_map(save_map(mapper, tmp_path / "m.rgmap"))
    for k, s in sset.by_keyframe.items():
        assert np.array_equal(back.supervision.by_keyframe[k].owned(), s.owned())
