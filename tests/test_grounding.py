"""End to end grounding on the session scene with oracle supervision: the grounded group's box and
masks match the ground truth; absent and bad queries fail with a reason; masks for any camera."""
import numpy as np
import torch
import pytest

from rg_core.config import RGConfig
from rg_core.eval.grounding import evaluate_queries, iou
from rg_core.grounding.boxes import box_iou_aabb
from rg_core.grounding.pipeline import Grounder


def test_explicit_queries_find_each_object(grounder, synth_scene):
    ious, vis = [], []
    for o in synth_scene.objects:
        r = grounder.ground(o.name, mode="explicit")
        assert r.success, r.message
        assert r.target == o.name and r.objects and 0.0 <= r.confidence <= 1.0
        ob = r.objects[0]
        assert len(ob.gaussian_ids) == len(ob.points) == len(ob.colors) > 0
        assert np.isfinite(ob.points).all() and ob.colors.dtype == np.uint8
        ious.append(box_iou_aabb(ob.aabb_min, ob.aabb_max, o.aabb_min, o.aabb_max))
        assert set(r.timings) >= {"reason", "reference_view", "relevancy", "cluster", "group", "total"}
    print("box IoU per object", np.round(ious, 3))
    # Gaussians cover only the observed surface of an object (its ground-truth box is whole), and
    # this scene is tiny (objects span 10-20 px): every group must overlap its object's box.
    assert min(ious) > 0.05 and np.mean(ious) > 0.15, ious


def test_groups_keep_the_members_a_robust_spread_cut_would_drop(grounder, synth_scene, monkeypatch):
    """The 3-MAD cut is off by default (it took small objects' lopsided parts); with it on, the
    group is the default group minus exactly what robust_inliers drops."""
    from rg_core.grounding.boxes import robust_inliers
    assert grounder.gcfg.outlier_mads == 0.0
    means = grounder.mapper.gaussians.means.detach().numpy()
    whole = {o.name: grounder.ground(o.name, mode="explicit").objects[0].gaussian_ids for o in synth_scene.objects}
    monkeypatch.setattr(grounder.gcfg, "outlier_mads", 1.0)
    cut_any = False
    for name, ids in whole.items():
        cut = grounder.ground(name, mode="explicit").objects[0].gaussian_ids
        np.testing.assert_array_equal(cut, ids[robust_inliers(means[ids], 1.0)])
        cut_any |= len(cut) < len(ids)
    assert cut_any, "at 1 MAD some group should lose members: the default must not have cut them already"


def test_masks_on_test_views(grounder, synth_scene):
    ev = evaluate_queries(grounder, synth_scene, implicit_per_object=0)
    print(ev["explicit"], ev["box_iou"])
    assert ev["explicit"]["pairs"] >= 6
    # Measured on this 160x120 scene after 200 field steps: visible 41-46, amodal 33; a wrong group
    # scores about 0 (benchmarks/bench_grounding.py reports the full-size figures).
    assert ev["explicit"]["target_accuracy"] == 100.0 and ev["explicit"]["success_rate"] == 100.0
    assert ev["explicit"]["miou_visible"] >= 30, ev["explicit"]
    assert ev["explicit"]["miou_amodal"] >= 25, ev["explicit"]
    # The test views' own depth sharpens the visible masks (what the node does with its frame).
    assert ev["explicit"]["miou_visible_depth"] >= ev["explicit"]["miou_visible"], ev["explicit"]   # 85.0 vs 77.6


def test_scenes_without_amodal_masks_report_amodal_as_missing(grounder, synth_scene):
    """YCB-Video ships visible masks only: amodal mIoU is nan there, never a made-up figure, and the
    visible figures are those of the same views with amodal masks."""
    import dataclasses

    bare = dataclasses.replace(synth_scene, test=[dataclasses.replace(f, complete_mask_dir=None) for f in synth_scene.test])
    assert not bare.test[0].has_amodal_masks()
    full = evaluate_queries(grounder, synth_scene, implicit_per_object=0)["explicit"]
    ev = evaluate_queries(grounder, bare, implicit_per_object=0)
    assert np.isnan(ev["explicit"]["miou_amodal"]) and not np.isnan(full["miou_amodal"])
    assert ev["explicit"]["miou_visible"] == full["miou_visible"]
    assert all(np.isnan(o["miou_amodal"]) for o in ev["per_object"].values())
    # Views without depth: the depth-sharpened figure is missing too, never the rendered one again.
    flat = dataclasses.replace(synth_scene, test=[dataclasses.replace(f, depth_path=None) for f in synth_scene.test])
    nod = evaluate_queries(grounder, flat, implicit_per_object=0)["explicit"]
    assert np.isnan(nod["miou_visible_depth"]) and not np.isnan(full["miou_visible_depth"])
    assert nod["miou_visible"] == full["miou_visible"]


def test_a_name_two_objects_share_is_asked_once_and_scored_against_the_one_found(grounder, synth_scene):
    """A room holds two remote controls: "remote control" is right for either. Asked once, scored
    against the one the answer's box overlaps; asked of each, one of them scored 0 by construction."""
    import dataclasses

    from rg_core.io.scene import Query

    a, b = synth_scene.objects[:2]
    twin = dataclasses.replace(b, name=a.name)   # b now carries a's name (its pixels and box stay b's)
    scene = dataclasses.replace(synth_scene, objects=[a, twin], queries=[Query(a.id, a.name, []), Query(b.id, a.name, [])])
    ev = evaluate_queries(grounder, scene, implicit_per_object=0)
    alone = evaluate_queries(grounder, dataclasses.replace(synth_scene, objects=[a], queries=[Query(a.id, a.name, [])]),
                             implicit_per_object=0)
    assert ev["queries_asked_of_several"] == 1 and alone["queries_asked_of_several"] == 0
    assert ev["explicit"]["queries"] == 1
    assert ev["explicit"]["pairs"] == alone["explicit"]["pairs"]
    assert ev["explicit"]["miou_visible"] == alone["explicit"]["miou_visible"] >= 30


def test_masks_of_a_second_instance_do_not_vote(grounder, synth_scene):
    """Two objects of one name (b's masks carry a's name): a keyframe's best mask of the name may
    show the other one, which sees this one's Gaussians outside it and would carve them away. Only
    masks that overlap the reference mask in 3D vote (`ground.instance_overlap`); 0 lets each
    keyframe's best mask vote, whichever instance it shows."""
    from rg_core.grounding import stages

    a, b = synth_scene.objects[:2]
    sup = grounder.mapper.supervision.by_keyframe
    unit = lambda t: torch.nn.functional.normalize(t.float(), dim=-1)
    e_a, e_b = unit(grounder.encode([a.name, b.name]))
    rows = {o.id: {k: np.flatnonzero((unit(s.embeddings) @ e).numpy() > 0.999) for k, s in sup.items()}
            for o, e in ((a, e_a), (b, e_b))}
    a_row = next(s.embeddings[rows[a.id][k][0]].clone() for k, s in sup.items() if len(rows[a.id][k]))
    saved = {k: s.embeddings.clone() for k, s in sup.items()}
    shown_by = lambda oid: {sup[k].masks[i].tobytes() for k, ii in rows[oid].items() for i in ii}
    views, before = {}, grounder.gcfg.instance_overlap
    try:
        for k, s in sup.items():
            s.embeddings[rows[b.id][k]] = a_row
        ref = stages.reference(grounder, a.name)
        mine = next(o.id for o in (a, b) if ref.mask.numpy().tobytes() in shown_by(o.id))
        other = b.id if mine == a.id else a.id
        # The reference's own masks a little less like the name: where both show, the other is best.
        u = unit(a_row)
        w = unit(e_b - (e_b @ u) * u)                                  # a unit vector orthogonal to u
        for k, s in sup.items():
            s.embeddings[rows[mine][k]] = (0.99 * u + 0.141 * w).to(s.embeddings.dtype)   # cosine 0.99
        ref.candidates = stages.mask_candidates(grounder, ref.target)
        assert ref.similarity - 0.02 <= min(float(unit(s.embeddings[i]) @ ref.target)
                                           for k, s in sup.items() for i in rows[mine][k]) < ref.similarity
        for overlap in (0.5, 0.0):
            grounder.gcfg.instance_overlap = overlap
            views[overlap] = [v.mask.tobytes() for v in stages.carve_views(grounder, ref)]
    finally:
        grounder.gcfg.instance_overlap = before
        for k, s in sup.items():
            s.embeddings = saved[k]
    seen = sum(len(ii) > 0 for ii in rows[mine].values())
    assert len(views[0.5]) >= min(seen, grounder.gcfg.carve_views) // 2
    assert all(m in shown_by(mine) for m in views[0.5])
    assert sum(m in shown_by(other) for m in views[0.0]) >= 2


def test_amodal_mask_covers_the_visible_mask(grounder, synth_scene):
    o = synth_scene.objects[0]
    r = grounder.ground(o.name, mode="explicit")
    f = synth_scene.test[0]
    amodal, visible = grounder.masks(r, f.intrinsics.K, f.cam_to_world, 160, 120)
    assert amodal.shape == visible.shape == (120, 160) and amodal.dtype == bool
    if visible.any():
        assert (visible & amodal).sum() >= 0.9 * visible.sum()
    # A camera looking away sees nothing of the group.
    away = f.cam_to_world.copy()
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    a2, v2 = grounder.masks(r, f.intrinsics.K, away, 160, 120)
    assert not v2.any()


@pytest.mark.parametrize("query, why", [("", "empty query"), ("x" * 1_000_000, "characters long"),
                                         ("   ", "empty query")])
def test_bad_queries_fail_with_a_reason(grounder, query, why):
    r = grounder.ground(query)
    assert not r.success and why in r.message


def test_absent_object_is_not_grounded(grounder):
    r = grounder.ground("a giraffe")
    assert not r.success and r.message and not r.objects


def test_before_training_the_grounder_says_why(synth_scene):
    from rg_core.map.mapper import Mapper

    r = Grounder(Mapper(), None, RGConfig(), reasoner=object(), text_encoder=lambda t: None).ground("mug")
    assert not r.success and "empty" in r.message


def test_iou_helper():
    a = np.zeros((4, 4), bool)
    a[:2] = True
    assert iou(a, a) == 1.0 and iou(a, ~a) == 0.0 and iou(np.zeros_like(a), np.zeros_like(a)) == 1.0


class _ImageReasoner:
    """The text reasoner behind an image reasoner's interface, recording the picture each call gets."""

    def __init__(self, accepts_images=True):
        from rg_core.perception.reasoning import TextReasoner

        self.inner, self.accepts_images, self.images = TextReasoner(), accepts_images, []

    def reason(self, query, vocabulary, image=None, mode="auto"):
        self.images.append(image)
        return self.inner.reason(query, vocabulary, image=None, mode=mode)


def test_image_reasoner_is_shown_the_scene(oracle_field, synth_scene):
    """An LVLM reasoner gets keyframes of the map (2 x 2 tiles of the first, last and evenly spaced
    keyframes, exact pixels) for implicit queries; explicit queries and text-only reasoners get none."""
    field, embed = oracle_field
    rs = _ImageReasoner()
    g = Grounder(field.mapper, field, RGConfig(), reasoner=rs, text_encoder=embed,
                 scene_names=[o.name for o in synth_scene.objects])
    obj = synth_scene.objects[0]
    r = g.ground(f"the {obj.name}", mode="implicit")
    assert r.success and r.target == obj.name
    img = rs.images[-1]
    kfs = field.mapper.keyframes
    h, w = kfs[0].rgb.shape[:2]
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.shape == (2 * h, 2 * w, 3)
    picks = [kfs[round(i)] for i in np.linspace(0, len(kfs) - 1, 4)]
    tiles = [img[:h, :w], img[:h, w:], img[h:, :w], img[h:, w:]]
    for kf, tile in zip(picks, tiles):
        np.testing.assert_array_equal(tile, (kf.rgb.clamp(0, 1) * 255).round().to(torch.uint8).numpy())
    g.ground(obj.name, mode="explicit")
    assert rs.images[-1] is None
    text_only = _ImageReasoner(accepts_images=False)
    Grounder(field.mapper, field, RGConfig(), reasoner=text_only, text_encoder=embed).ground(
        f"the {obj.name}", mode="implicit")
    assert text_only.images == [None]
    # one keyframe: that keyframe alone
    one = Grounder(type("M", (), {"keyframes": kfs[:1]})(), None, RGConfig(), reasoner=rs, text_encoder=embed)
    assert one.scene_image().shape == (h, w, 3)


def test_vote_border_is_measured_from_the_map(grounder):
    """Synthetic renders: masks and depth agree, so the votes grow no mask (the results of every
    synthetic figure stay as they were); the same map with every supervision mask shifted by
    2 px, as a misregistered sensor would give, grows them by 2."""
    import copy

    assert grounder.gcfg.vote_border_px == -1 and grounder.vote_border() == 0
    mapper = copy.copy(grounder.mapper)
    sup = copy.deepcopy(grounder.mapper.supervision)
    for ks in sup.by_keyframe.values():
        ks.masks = np.roll(ks.masks, (2, 2), axis=(1, 2))
    mapper.supervision = sup
    g = Grounder(mapper, grounder.field, RGConfig())
    assert g.vote_border() == 2
    cfg = RGConfig()
    cfg.ground.vote_border_px = 1
    fixed = Grounder(mapper, grounder.field, cfg)
    assert fixed.vote_border() == 1


def test_map_resolution_is_not_shrunk_by_clumped_clones(grounder):
    """A photo fit's density control clones Gaussians in place: the map's resolution (the links that
    keep a group one piece) stays at least the Gaussians' median size, not the clones' 0.1 mm."""
    import copy

    from rg_core.geometry.points import map_spacing

    mapper = copy.copy(grounder.mapper)
    gs = copy.deepcopy(grounder.mapper.gaussians)
    gs.means = torch.cat([gs.means, gs.means + 1e-4])
    for k in ("log_scales", "quats", "opacity_logits", "colors"):
        setattr(gs, k, torch.cat([getattr(gs, k)] * 2))
    mapper.gaussians = gs
    g = Grounder(mapper, grounder.field, RGConfig())
    assert map_spacing(gs.means.numpy()) < 2e-4
    size = float(gs.scales.max(1).values.median())
    assert g.spacing() >= size > 10 * map_spacing(gs.means.numpy())
    assert grounder.spacing() >= map_spacing(grounder.mapper.gaussians.means.detach().numpy())


@pytest.mark.parametrize("built, expect", [({}, 0.02), ({"kind": "rgbd"}, 0.02),
                                           ({"kind": "photo", "photo": {"depth_resolution_m": 0.15}}, 0.15),
                                           ({"kind": "photo", "photo": {"depth_resolution_m": 0.005}}, 0.02)])
def test_votes_allow_a_photo_maps_depth_resolution(grounder, built, expect):
    """A photo map's keyframe depth is its own expected depth, and the photos place an object's
    Gaussians only as well as their baseline allows: the votes' depth test allows that much, never
    less than 2 cm."""
    import copy

    mapper = copy.copy(grounder.mapper)
    mapper.built = built
    assert Grounder(mapper, grounder.field, RGConfig()).vote_depth_tol() == pytest.approx(expect)


@pytest.mark.parametrize("built, link_spacing, expect", [({}, 3.0, None), ({"kind": "rgbd"}, 3.0, None),
                                                         ({"kind": "photo", "photo": {"depth_resolution_m": 0.15}}, 3.0, 0.15),
                                                         ({"kind": "photo", "photo": {"depth_resolution_m": 1e-4}}, 3.0, None),
                                                         ({"kind": "photo", "photo": {"depth_resolution_m": 0.15}}, 0.0, 0.0)])
def test_links_are_no_finer_than_a_photo_maps_depth_resolution(grounder, built, link_spacing, expect):
    """The photos place a Gaussian only to their depth resolution along its ray: the links that keep a
    group one piece step at least that far (an object whose surface the fit left in two layers 10 cm
    apart stays whole), RGB-D maps keep link_spacing x spacing, and link_spacing 0 keeps no links."""
    import copy
    import dataclasses

    from rg_core.grounding.boxes import connected_to

    mapper = copy.copy(grounder.mapper)
    mapper.built = built
    cfg = RGConfig()
    cfg.ground = dataclasses.replace(cfg.ground, link_spacing=link_spacing)
    g = Grounder(mapper, grounder.field, cfg)
    link = g.link_length()
    assert link == pytest.approx(3.0 * g.spacing() if expect is None else expect)
    if link > 0:
        layers = np.array([[x, 0.0, z] for z in (1.0, 1.1) for x in np.arange(0.0, 0.05, 0.005)])   # [20, 3]
        whole = connected_to(layers, layers[0], link).all()
        assert whole == (link >= 0.1), (link, whole)


def test_text_embeddings_kept_are_bounded(grounder, monkeypatch):
    """Hours of distinct queries: the Grounder keeps the newest TEXT_CACHE_SIZE text embeddings, and
    an evicted text embeds again to the same row."""
    import rg_core.grounding.texts as texts

    monkeypatch.setattr(texts, "TEXT_CACHE_SIZE", 8)
    first = grounder.encode(["query number 0"])
    for i in range(1, 30):
        assert grounder.encode([f"query number {i}", "query number 0"]).shape[0] == 2
        assert len(grounder._text_cache) <= 8
    grounder._text_cache.clear()
    torch.testing.assert_close(grounder.encode(["query number 0"]), first)


def test_a_larger_map_is_culled_around_the_reference_view(grounder, synth_scene, oracle_field):
    """The session map tiled 4x side by side (a larger area at the same density, the keyframes in the
    first copy): single-object queries cluster only within cull_radius of the reference mask (the
    other copies are left out) and find the same objects, inside the first copy."""
    from rg_core.perception.reasoning import TextReasoner
    from rg_core.report.inputs import resized_map

    field, embed = oracle_field
    N = len(field.mapper.gaussians)
    m, f = resized_map(field.mapper, field, 4 * N, tile=True)
    assert len(m.gaussians) == 4 * N
    torch.testing.assert_close(m.gaussians.means[:N], field.mapper.gaussians.means)   # copy 0 in place
    big = Grounder(m, f, RGConfig(), reasoner=TextReasoner(), text_encoder=embed,
                   scene_names=[o.name for o in synth_scene.objects])
    for o in synth_scene.objects[:3]:
        r, r0 = big.ground(o.name, mode="explicit"), grounder.ground(o.name, mode="explicit")
        assert r.success and r.target == r0.target == o.name, r.message
        assert r.objects[0].gaussian_ids.max() < N                                       # nothing from other copies
    keys = [k for k in big.cache.tables["groups"]]
    assert keys and all(k[2] is not None for k in keys)                                  # clustered over a region
    assert np.unpackbits(np.frombuffer(keys[0][2], np.uint8))[:4 * N].sum() <= N         # at most copy 0


def test_the_peak_lies_where_the_map_renders_what_the_sensor_read(grounder, synth_scene):
    """A reference-mask pixel where the map renders another surface than the keyframe's reading (a
    thin rim showing the table behind, a floater in front) would anchor the group there: the peak
    skips such pixels; with none left, or no readings at all, it takes the whole mask."""
    from rg_core.grounding import stages

    name = synth_scene.objects[0].name
    target = grounder._reason(name, "explicit").target
    ref = stages.reference(grounder, target)
    kf, mask = ref.keyframe, ref.mask
    saved = kf.depth.clone()
    try:
        kf.depth.fill_(float("nan"))                         # no readings: the rule cannot apply
        free = stages.peak(grounder, ref, target)
        kf.depth.copy_(saved)
        pk = stages.peak(grounder, ref, target)
        assert mask[pk.py, pk.px]
        # The sensor reads 0.5 m beyond the render around the peak: the peak moves off that block
        # onto a pixel whose rendered surface is the reading, and anchors there.
        ys, xs = slice(max(pk.py - 3, 0), pk.py + 4), slice(max(pk.px - 3, 0), pk.px + 4)
        assert int(mask.sum()) > int(mask[ys, xs].sum()) + 10
        z = (pk.render.depth / pk.render.alpha.clamp(min=1e-6)).detach()
        kf.depth[ys, xs] = z[ys, xs] + 0.5
        moved = stages.peak(grounder, ref, target)
        assert mask[moved.py, moved.px] and not (ys.start <= moved.py < ys.stop and xs.start <= moved.px < xs.stop)
        d = float(kf.depth[moved.py, moved.px])
        c = grounder.mapper.cfg
        assert d <= 0 or abs(float(z[moved.py, moved.px]) - d) <= max(c.depth_error_rel * d, c.depth_error_abs)
        kf.depth.copy_(z + 5.0)                              # every reading disagrees: the whole mask
        every = stages.peak(grounder, ref, target)
        assert (every.px, every.py) == (free.px, free.py)
    finally:
        kf.depth.copy_(saved)


@pytest.mark.parametrize("share, expect_visible", [(0.4, True), (0.5, False)])
def test_visible_mask_follows_the_share_threshold(share, expect_visible):
    """A half-transparent group Gaussian (opacity 0.45) in front of an opaque wall: at its centre the
    full render is opaque and the group holds 45 % of the blending weight, so it is visible below a
    0.45 share and not above; its amodal mask (alpha 0.45 < mask_alpha) stays empty either way."""
    from rg_core.grounding.result import GroundedObject, GroundingResult
    from rg_core.map.mapper import Mapper

    mapper = Mapper()
    mapper.gaussians.append(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([0.05]), torch.ones(1, 3), opacity=0.45)
    mapper.gaussians.append(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([1.0]), torch.zeros(1, 3), opacity=0.999)
    cfg = RGConfig()
    cfg.ground.visible_share = share
    z3 = np.zeros(3)
    ob = GroundedObject(gaussian_ids=np.array([0]), points=np.zeros((1, 3), np.float32),
                        colors=np.zeros((1, 3), np.uint8), aabb_min=z3, aabb_max=z3, obb_center=z3,
                        obb_rotation=np.eye(3), obb_extent=z3)
    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    g = Grounder(mapper, None, cfg)
    amodal, visible = g.masks(GroundingResult(True, "", objects=[ob]), K, np.eye(4), 64, 64)
    full = mapper.render(K, np.eye(4), 64, 64)
    assert float(full.alpha[32, 32]) > 0.99          # the wall behind makes the pixel opaque
    assert bool(visible[32, 32]) is expect_visible
    assert not amodal.any()
    # Far from the group the wall alone covers the pixel: never the group's.
    assert not visible[0, 0] and not visible[63, 63]


def test_visible_mask_follows_the_cameras_depth_image():
    """An opaque group Gaussian at 1 m before a wall at 2 m (the rest of the map). The camera's depth
    image shows the object smaller than the blob renders (rows and cols 28-35): pixels whose reading
    is the wall's leave the visible mask, the object's stay; the amodal mask ignores depth;
    visible_depth_tol 0 renders only."""
    from rg_core.grounding.result import GroundedObject, GroundingResult
    from rg_core.map.mapper import Mapper

    mapper = Mapper()
    mapper.gaussians.append(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([0.05]), torch.ones(1, 3), opacity=0.99)
    mapper.gaussians.append(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([1.0]), torch.zeros(1, 3), opacity=0.999)
    z3 = np.zeros(3)
    ob = GroundedObject(gaussian_ids=np.array([0]), points=np.zeros((1, 3), np.float32),
                        colors=np.zeros((1, 3), np.uint8), aabb_min=z3, aabb_max=z3, obb_center=z3,
                        obb_rotation=np.eye(3), obb_extent=z3)
    res = GroundingResult(True, "", objects=[ob])
    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    obj = np.zeros((64, 64), bool)
    obj[28:36, 28:36] = True
    depth = np.where(obj, 1.0, 2.0).astype(np.float32)
    cfg = RGConfig()
    g = Grounder(mapper, None, cfg)
    amodal0, raw = g.masks(res, K, np.eye(4), 64, 64)
    amodal, visible = g.masks(res, K, np.eye(4), 64, 64, depth)
    assert (raw & ~obj).sum() > 20 and (raw & obj).sum() == obj.sum()    # the render bleeds onto the wall
    np.testing.assert_array_equal(visible, obj)
    np.testing.assert_array_equal(amodal, amodal0)
    cfg.ground.visible_depth_tol = 0.0
    np.testing.assert_array_equal(Grounder(mapper, None, cfg).masks(res, K, np.eye(4), 64, 64, depth)[1], raw)


def test_rg_ground_view_masks_follow_the_keyframes_depth(tmp_path):
    """`rg ground --view I` renders for keyframe I and hands its depth and colour images to the masks
    (as the node does its current frame's): the visible mask is the sensed object, not the blob the
    render bleeds; --pose has no images and renders only."""
    import argparse
    import json

    from rg_core.cli.grounding import _camera_from_args
    from rg_core.grounding.result import GroundedObject, GroundingResult
    from rg_core.map.keyframes import Keyframe
    from rg_core.map.mapper import Mapper

    mapper = Mapper()
    mapper.gaussians.append(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([0.05]), torch.ones(1, 3), opacity=0.99)
    mapper.gaussians.append(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([1.0]), torch.zeros(1, 3), opacity=0.999)
    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    obj = np.zeros((64, 64), bool)
    obj[28:36, 28:36] = True
    rgb = torch.from_numpy(np.repeat(np.where(obj, 0.8, 0.2)[..., None], 3, 2).astype(np.float32))   # a light object
    mapper.keyframes.append(Keyframe(7, 0.0, np.eye(4), K, rgb,
                                     torch.from_numpy(np.where(obj, 1.0, 2.0).astype(np.float32))))
    z3 = np.zeros(3)
    res = GroundingResult(True, "", objects=[GroundedObject(
        gaussian_ids=np.array([0]), points=np.zeros((1, 3), np.float32), colors=np.zeros((1, 3), np.uint8),
        aabb_min=z3, aabb_max=z3, obb_center=z3, obb_rotation=np.eye(3), obb_extent=z3)])
    g = Grounder(mapper, None, RGConfig())
    Kv, c2w, w, h, depth, image = _camera_from_args(argparse.Namespace(pose=None, view=7), g, res)
    assert (w, h) == (64, 64) and depth is not None and image.shape == (64, 64, 3)
    _, visible = g.masks(res, Kv, c2w, w, h, depth, image)
    np.testing.assert_array_equal(visible, obj)
    pose = tmp_path / "cam.json"
    pose.write_text(json.dumps({"K": K.tolist(), "cam_to_world": np.eye(4).tolist(), "width": 64, "height": 64}))
    *cam, depth, image = _camera_from_args(argparse.Namespace(pose=str(pose), view=None), g, res)
    assert depth is None and image is None
    _, raw = g.masks(res, *cam)
    assert (raw & ~obj).sum() > 20


def test_instance_groups_are_read_inside_the_interval_training_samples_above_s_star(grounder, synth_scene):
    """The reference mask groups its object at scales from its own s* up to the view's next mask
    scale (GARField's interval sampling); at s* itself the features sit on the step between the two
    sides. The groups are read at that interval's middle."""
    import numpy as np

    from rg_core.field.sampling import interval_centre
    from rg_core.grounding import stages

    assert interval_centre([0.065, 0.036, 0.089, 0.065, 0.139], 0.065) == pytest.approx((0.065 + 0.089) / 2, rel=1e-6)
    assert interval_centre([0.036, 0.139], 0.139) == pytest.approx(0.139 * 1.25, rel=1e-6)   # the largest: up to 1.5 s*
    assert interval_centre([0.036, 0.139], 0.05) == 0.05                                      # not a scale of the view
    assert interval_centre([], 0.05) == 0.05
    ref = stages.reference(grounder, synth_scene.objects[0].name)
    assert not isinstance(ref, str), ref
    u = np.unique(grounder.mapper.supervision.by_keyframe[ref.keyframe.index].scales)
    above = u[u > np.float32(ref.scale)]
    top = above[0] if len(above) else 1.5 * ref.scale
    assert ref.scale < ref.group_scale < top and ref.group_scale == pytest.approx((ref.scale + top) / 2, rel=1e-5)
