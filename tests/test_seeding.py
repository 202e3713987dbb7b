"""Seeding: one seed per block, the local range of an image, far surfaces seeded finer."""
import torch

from rg_core.config import MapConfig
from rg_core.map.frames import prepare_frame
from rg_core.map.mapper import Mapper
from rg_core.map.seeding import local_range, seed_pixels


def test_seed_pixels_one_per_block_nearest_the_centre():
    m = torch.zeros(8, 12, dtype=torch.bool)
    m[0:4, 0:4] = True          # a full block: its centre-most pixel
    m[5, 9] = True              # a single pixel: itself
    vs, us = seed_pixels(m, 4)
    got = sorted(zip(vs.tolist(), us.tolist()))
    assert len(got) == 2 and got[1] == (5, 9)
    assert got[0][0] in (1, 2) and got[0][1] in (1, 2)
    assert len(seed_pixels(torch.zeros(5, 5, dtype=torch.bool), 4)[0]) == 0
    assert len(seed_pixels(torch.ones(6, 6, dtype=torch.bool), 1)[0]) == 36


def test_local_range_ignores_invalid_pixels():
    d = torch.full((6, 6), 2.0)
    d[:, 3:] = 0.0                          # invalid: no step between 2 m and "no depth"
    assert float(local_range(d, 3, d > 0).max()) == 0.0
    d[:, 4:] = 3.0
    r = local_range(d, 3, d > 0)
    assert float(r[0, 1]) == 0.0 and float(r[0, 3]) == 1.0 and float(r[0, 5]) == 0.0   # the step spans the gap


def test_far_surfaces_are_seeded_at_half_the_stride(synth_scene):
    """seed_spacing: pixels whose stride-4 block spans more than it (far ones) get stride-2 seeds,
    each scaled to its own stride; near ones are seeded as before; 0 (off) seeds exactly as before."""
    f = synth_scene.train[0]
    fr = prepare_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, f.stamp, 160)
    z = torch.from_numpy(fr.depth)
    valid = z > 0
    fx = float(fr.K[0, 0])
    split = float(z[valid].median())                       # half the view beyond it
    counts, maps = {}, {}
    for name, kw in {"coarse": dict(seed_stride=4), "split": dict(seed_stride=4, seed_spacing=4 * split / fx),
                     "fine": dict(seed_stride=2), "all far": dict(seed_stride=4, seed_spacing=1e-6),
                     "none far": dict(seed_stride=4, seed_spacing=1e3)}.items():
        m = Mapper(MapConfig(width=160, **kw))
        counts[name], _ = m._seed(fr, valid)
        maps[name] = m
    assert counts["coarse"] < counts["split"] < counts["fine"], counts
    assert counts["all far"] == counts["fine"] and counts["none far"] == counts["coarse"]
    g = maps["split"].gaussians
    R, t = torch.as_tensor(f.cam_to_world[:3, :3]).float(), torch.as_tensor(f.cam_to_world[:3, 3]).float()
    depth = ((g.means.detach() - t) @ R)[:, 2]
    stride = g.scales.detach().amax(-1) / (0.6 * depth / fx)
    fine = torch.round(stride) == 2
    assert set(torch.round(stride).long().unique().tolist()) == {2, 4}
    assert bool((depth[fine] > split * 0.999).all()) and bool((depth[~fine] <= split * 1.001).all())
    off = Mapper(MapConfig(width=160, seed_stride=4, seed_spacing=0.0))
    assert off._seed(fr, valid)[0] == counts["coarse"]
    assert torch.equal(off.gaussians.means, maps["coarse"].gaussians.means)
