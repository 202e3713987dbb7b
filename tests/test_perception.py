"""2D supervision pieces: physical scale of masks, PCA, the offline RGB-D mask generator."""
import numpy as np
import pytest
import torch

from rg_core.perception.masks import make_mask_generator
from rg_core.perception.pca import PCA, IncrementalPCA
from rg_core.perception.scale import MaskScaleError, mask_scale

K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])


def plate(side: float, z: float, shape=(240, 320)):
    """A fronto-parallel square plate of `side` metres at depth z: its mask and depth."""
    H, W = shape
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    x, y = (u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1]
    m = (np.abs(x) <= side / 2) & (np.abs(y) <= side / 2)
    return m, np.where(m, z, 0.0).astype(np.float32)


@pytest.mark.parametrize("side, z", [(0.05, 0.5), (0.2, 1.0), (0.6, 2.5)])
def test_scale_of_known_shapes(side, z):
    m, d = plate(side, z)
    expected = side / np.sqrt(6.0)  # uniform square: var L^2/12 on x and y
    assert mask_scale(m, d, K) == pytest.approx(expected, rel=0.03)


def test_scale_ignores_flying_pixels_and_uses_rendered_depth():
    m, d = plate(0.2, 1.0)
    clean = mask_scale(m, d, K)
    noisy = d.copy()
    vs, us = np.nonzero(m)
    pick = np.random.default_rng(0).choice(len(vs), len(vs) // 20, replace=False)
    noisy[vs[pick], us[pick]] = 3.0  # 5% flying pixels 2 m behind
    assert mask_scale(m, noisy, K) == pytest.approx(clean, rel=0.05)
    holes = d.copy()
    holes[::2] = 0.0  # half the sensor depth missing: the rendered depth fills it
    assert mask_scale(m, holes, K, rendered_depth=d) == pytest.approx(clean, rel=1e-6)


def test_scale_rejects_bad_masks():
    m, d = plate(0.2, 1.0)
    one = np.zeros_like(m)
    one[120, 160] = True
    with pytest.raises(MaskScaleError, match="1 pixels with valid depth, need at least 20"):
        mask_scale(one, d, K)
    with pytest.raises(MaskScaleError, match="0 pixels with valid depth"):
        mask_scale(m, np.zeros_like(d), K)
    with pytest.raises(MaskScaleError, match="same size"):
        mask_scale(m[:10], d, K)


def test_pca_round_trip_and_explained_variance():
    g = torch.Generator().manual_seed(0)
    basis = torch.randn(8, 384, generator=g)
    x = torch.randn(200, 8, generator=g) @ basis + 3.0   # rank 8 around a non-zero mean
    p = PCA.fit(x, 64)
    assert p.dim == 64 and p.components.shape == (64, 384)
    z = p.transform(x)
    assert z.shape == (200, 64)
    torch.testing.assert_close(p.inverse(z), x, atol=1e-3, rtol=1e-4)
    assert float(p.explained_variance_ratio[:8].sum()) > 0.999
    back = PCA.from_state_dict(p.state_dict())
    torch.testing.assert_close(back.transform(x), z)
    with pytest.raises(ValueError, match="finite"):
        PCA.fit(torch.full((3, 4), float("nan")))


def test_incremental_pca_refits_as_masks_arrive():
    g = torch.Generator().manual_seed(1)
    inc = IncrementalPCA(k=16, refit_growth=1.5, min_fit=8)
    assert not inc.add(torch.randn(4, 32, generator=g))
    assert inc.add(torch.randn(6, 32, generator=g)) and inc.version == 1
    assert not inc.add(torch.randn(2, 32, generator=g))       # 12 < 1.5 x 10
    assert inc.add(torch.randn(5, 32, generator=g)) and inc.version == 2 and inc.pca.n_fit == 17


def test_rgbd_masks_find_objects(synth_scene):
    gen = make_mask_generator("rgbd")
    hits = total = 0
    for f in synth_scene.frames[::2]:
        rgb, depth, vis = f.load_rgb(), f.load_depth(), f.load_visible_mask()
        masks = gen.generate(rgb, depth, f.intrinsics.K)
        assert 0 < len(masks) <= 40
        assert all(m.mask.shape == depth.shape and 0.0 <= m.score <= 1.0 and m.level in (0, 1, 2) for m in masks)
        for o in synth_scene.objects:
            gt = vis == o.id
            if gt.mean() < 0.005:
                continue
            total += 1
            best = max(float((m.mask & gt).sum() / (m.mask | gt).sum()) for m in masks)
            hits += best >= 0.5
    assert total >= 10 and hits / total >= 0.8, (hits, total)


def test_mask_generator_input_errors():
    gen = make_mask_generator("rgbd")
    rgb = np.zeros((20, 30, 3), np.uint8)
    with pytest.raises(ValueError, match="needs depth"):
        gen.generate(rgb)
    with pytest.raises(ValueError, match="does not match rgb"):
        gen.generate(rgb, np.ones((10, 10), np.float32), K)
    with pytest.raises(ValueError, match="rgb must be uint8"):
        gen.generate(rgb.astype(np.float32), np.ones((20, 30), np.float32), K)
    with pytest.raises(ValueError, match="unknown mask generator 'sam9'"):
        make_mask_generator("sam9")


def _table_with_flat_object(height: float, noise: float, seed: int = 0):
    """A grey table 0.6 m away filling the view, a red 60 x 40 px card `height` m thick on it, depth
    noise of std `noise` m: (rgb, depth, card mask)."""
    H, W = 240, 320
    rng = np.random.default_rng(seed)
    card = np.zeros((H, W), bool)
    card[100:140, 130:190] = True
    depth = np.full((H, W), 0.6) - height * card + rng.normal(0.0, noise, (H, W)) if noise else \
        np.full((H, W), 0.6) - height * card
    rgb = np.full((H, W, 3), 128, np.uint8)
    rgb[card] = (200, 30, 30)
    return rgb, depth.astype(np.float32), card


@pytest.mark.parametrize("height", [0.004, 0.006])
def test_a_flat_object_on_a_clean_table_is_not_swallowed_by_the_plane(height):
    # 4-6 mm is within RANSAC's 8 mm inlier distance: the plane's own residuals (none here) set the reach
    rgb, depth, card = _table_with_flat_object(height, 0.0)
    masks = make_mask_generator("rgbd").generate(rgb, depth, K)
    best = max(float((m.mask & card).sum() / (m.mask | card).sum()) for m in masks)
    assert best >= 0.9, best


def test_a_noisy_tables_plane_keeps_the_ransac_distance_and_few_inliers_fall_back():
    from rg_core.perception.masks.rgbd import RGBDMaskConfig, _refit

    cfg = RGBDMaskConfig()
    u, v = np.meshgrid(np.arange(320), np.arange(240))
    for noise, want in ((0.0, cfg.plane_min_distance), (0.003, cfg.plane_distance), (0.0005, 4 * 0.0005)):
        _, depth, _ = _table_with_flat_object(0.0, noise, seed=1)
        z = depth.astype(np.float64)
        pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], -1)
        dist0 = np.abs(z - 0.6)
        dist, reach = _refit(pts, dist0, dist0 < cfg.plane_distance, cfg)
        assert reach == pytest.approx(want, rel=0.15), (noise, reach)
        assert np.isfinite(dist).all() and np.median(dist) < max(noise, 1e-4)
    few = np.zeros((240, 320), bool)
    few[0, :2] = True
    dist, reach = _refit(pts, dist0, few, cfg)
    assert reach == cfg.plane_distance and dist is dist0
