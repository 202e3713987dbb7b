"""SAM backends: "sam_onnx" through its real loading and inference path on a small random model with
SAM's exact ONNX signatures (the test builds and exports it), its post-processing on hand-made inputs,
and the errors of both backends."""
import importlib.util

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from rg_core.perception.base import BackendError, Mask
from rg_core.perception.masks import make_mask_generator
from rg_core.perception.masks.sam import (
    SamOnnxGenerator,
    box_nms,
    mask_boxes,
    mask_nms,
    point_grid,
    preprocess,
    records_to_masks,
    resized_shape,
    stability_score,
)


class TinyEncoder(torch.nn.Module):
    """SAM's image encoder signature: [1, 3, 1024, 1024] -> image_embeddings [1, 256, 64, 64]."""

    def __init__(self):
        super().__init__()
        self.patch = torch.nn.Conv2d(3, 256, 16, stride=16)

    def forward(self, image):
        return torch.tanh(self.patch(image))


class TinyDecoder(torch.nn.Module):
    """SamOnnxModel's signature. Mask k of a prompt is a disc of radius r_k around its positive points
    (1024 frame), perturbed by a 1x1 conv of the embeddings; the IoU prediction depends on the point.
    `single_token` prepends a fourth output (SamOnnxModel with return_single_mask=False)."""

    def __init__(self, single_token: bool = False):
        super().__init__()
        self.single_token = single_token
        self.feat = torch.nn.Conv2d(256, 3, 1)
        self.register_buffer("radius", torch.tensor([70.0, 160.0, 400.0]).view(1, 3, 1, 1))
        self.register_buffer("slope", torch.tensor([6.0, 12.0, 30.0]).view(1, 3, 1, 1))
        c = (torch.arange(256, dtype=torch.float32) + 0.5) * 4.0  # low-res cell centres, 1024 frame
        self.register_buffer("gy", c.view(1, 1, 256, 1))
        self.register_buffer("gx", c.view(1, 1, 1, 256))
        self.iou_w = torch.nn.Parameter(torch.randn(3, 3))

    def forward(self, image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size):
        px, py = point_coords[..., 0, None, None], point_coords[..., 1, None, None]  # [B, N, 1, 1]
        d = torch.sqrt((self.gx - px) ** 2 + (self.gy - py) ** 2)  # [B, N, 256, 256]
        d = d + (point_labels != 1).float()[..., None, None] * 1e4  # only positive points
        d = d.min(1, keepdim=True).values  # [B, 1, 256, 256]
        f = F.interpolate(self.feat(image_embeddings), size=(256, 256), mode="bilinear", align_corners=False)
        low = (self.radius - d) / self.slope + 2.0 * f + has_mask_input * mask_input  # [B, 3, 256, 256]
        p = point_coords[:, 0] / 1024.0  # [B, 2]: first point
        feats = torch.stack([torch.sin(9.0 * p[:, 0]), torch.cos(7.0 * p[:, 1]), image_embeddings.mean().expand_as(p[:, 0])], -1)
        iou = torch.sigmoid(2.0 * feats @ self.iou_w + 1.0)  # [B, 3]
        if self.single_token:
            low = torch.cat([torch.full_like(low[:, :1], 5.0), low], 1)
            iou = torch.cat([torch.ones_like(iou[:, :1]), iou], 1)
        return self.postprocess(low, orig_im_size), iou, low

    @staticmethod
    def postprocess(masks, orig_im_size):
        """segment_anything/utils/onnx.py mask_postprocessing, verbatim in effect."""
        masks = F.interpolate(masks, size=(1024, 1024), mode="bilinear", align_corners=False)
        size = orig_im_size.to(torch.float32)
        pre = torch.floor(1024 / torch.max(size) * size + 0.5).to(torch.int64)
        masks = masks[..., : pre[0], : pre[1]]
        hw = orig_im_size.to(torch.int64)
        return F.interpolate(masks, size=(hw[0], hw[1]), mode="bilinear", align_corners=False)


def _export_decoder(dec, path, batch=None):
    """batch None: a dynamic batch axis; an int: exported with that fixed batch."""
    B = batch or 2
    args = (torch.randn(1, 256, 64, 64), torch.rand(B, 2, 2) * 1000, torch.tensor([[1.0, -1.0]] * B),
            torch.zeros(1, 1, 256, 256), torch.zeros(1), torch.tensor([96.0, 128.0]))
    axes = {"point_coords": {1: "n"}, "point_labels": {1: "n"}, "masks": {2: "h", 3: "w"}}
    if batch is None:
        for k in ("point_coords", "point_labels", "masks", "iou_predictions", "low_res_masks"):
            axes.setdefault(k, {})[0] = "b"
    torch.onnx.export(dec, args, str(path), input_names=["image_embeddings", "point_coords", "point_labels",
                                                         "mask_input", "has_mask_input", "orig_im_size"],
                      output_names=["masks", "iou_predictions", "low_res_masks"], dynamic_axes=axes,
                      opset_version=17, dynamo=False)


@pytest.fixture(scope="module")
def sam_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("sam")
    torch.manual_seed(0)
    enc, dec = TinyEncoder().eval(), TinyDecoder().eval()
    torch.onnx.export(enc, (torch.randn(1, 3, 1024, 1024),), str(d / "encoder.onnx"), input_names=["image"],
                      output_names=["image_embeddings"], opset_version=17, dynamo=False)
    _export_decoder(dec, d / "decoder.onnx")
    # Same weights, a fixed batch of 5 and the extra single-mask output first: must give the same masks.
    dec4 = TinyDecoder(single_token=True).eval()
    dec4.load_state_dict(dec.state_dict())
    _export_decoder(dec4, d / "decoder_b5_k4.onnx", batch=5)
    return d


def _image(h=96, w=128):
    """Synthetic scene: grey background, a red box, a green disc, a blue bar."""
    img = np.full((h, w, 3), 90, np.uint8)
    img[10:50, 10:60] = (220, 40, 40)
    yy, xx = np.mgrid[:h, :w]
    img[(yy - 60) ** 2 + (xx - 90) ** 2 < 22 ** 2] = (40, 200, 60)
    img[75:88, 5:120] = (30, 30, 210)
    return img


LOOSE = {"points_per_side": 8, "points_per_batch": 16, "pred_iou_thresh": 0.0, "stability_score_thresh": 0.0,
         "min_area": 0.0, "max_masks": 1000}


def _iou(a, b):
    return (a & b).sum() / max(1, (a | b).sum())


def test_sam_onnx_generates_valid_deduplicated_masks(sam_files):
    gen = make_mask_generator("sam_onnx", encoder_path=str(sam_files / "encoder.onnx"),
                              decoder_path=str(sam_files / "decoder.onnx"), **LOOSE)
    assert isinstance(gen, SamOnnxGenerator) and gen.batch == 16
    img = _image()
    out = gen.generate(img)
    assert len(out) >= 5 and all(isinstance(m, Mask) for m in out)
    for m in out:
        assert m.mask.dtype == bool and m.mask.shape == img.shape[:2] and m.mask.any()
        assert 0.0 <= m.score <= 1.0 and m.level in (0, 1, 2)
    assert {m.level for m in out} == {0, 1, 2}
    assert [m.score for m in out] == sorted((m.score for m in out), reverse=True)
    for i in range(len(out)):
        for j in range(i):
            assert _iou(out[i].mask, out[j].mask) <= gen.cfg.nms_iou
    # Different prompts give different masks: the grid found several distinct regions.
    assert len({m.mask.tobytes() for m in out}) == len(out)
    # Cap.
    capped = make_mask_generator("sam_onnx", encoder_path=str(sam_files / "encoder.onnx"),
                                 decoder_path=str(sam_files / "decoder.onnx"), **{**LOOSE, "max_masks": 3})
    assert len(capped.generate(img)) == 3
    # A decoder with a fixed batch of 5 (64 prompts: the last call is padded) and the single-mask
    # output first gives the same result.
    b5 = make_mask_generator("sam_onnx", encoder_path=str(sam_files / "encoder.onnx"),
                             decoder_path=str(sam_files / "decoder_b5_k4.onnx"), **LOOSE)
    assert b5.batch == 5
    again = b5.generate(img)
    assert len(again) == len(out)
    for a, b in zip(out, again):
        assert np.array_equal(a.mask, b.mask) and a.level == b.level and a.score == pytest.approx(b.score, abs=1e-6)


def test_sam_onnx_thresholds_filter(sam_files):
    kw = {"encoder_path": str(sam_files / "encoder.onnx"), "decoder_path": str(sam_files / "decoder.onnx")}
    img = _image()
    # Nothing is suppressed: the counts are those of the filters. A 5 x 5 grid keeps the test short.
    no_nms = {**LOOSE, "nms_iou": 1.0, "points_per_side": 5}
    gen = make_mask_generator("sam_onnx", **kw, **no_nms)
    emb = gen.embed(img)
    pts = point_grid(5) * np.array([img.shape[1], img.shape[0]])
    logits, iou = gen.predict_points(emb, pts, img.shape[:2])  # [25, 3, H, W], [25, 3]
    assert logits.shape == (25, 3, *img.shape[:2]) and iou.shape == (25, 3)
    nonempty = (logits > 0).any((2, 3))
    assert len(gen.generate(img)) == nonempty.sum()
    stab = stability_score(logits)  # [25, 3]
    for name, values in (("pred_iou_thresh", iou), ("stability_score_thresh", stab)):
        t = float(np.median(values[nonempty]))
        n = len(make_mask_generator("sam_onnx", **kw, **{**no_nms, name: t}).generate(img))
        expect = (values > t if name == "pred_iou_thresh" else values >= t) & nonempty
        assert 0 < n < nonempty.sum() and n == expect.sum(), name
    for name in ("pred_iou_thresh", "stability_score_thresh"):
        assert make_mask_generator("sam_onnx", **kw, **{**no_nms, name: 1.01}).generate(img) == []
    # Tiny masks are removed.
    areas = (logits > 0).sum((2, 3))[nonempty]
    t = float(np.median(areas)) / (img.shape[0] * img.shape[1])
    n = len(make_mask_generator("sam_onnx", **kw, **{**no_nms, "min_area": t}).generate(img))
    assert n == (areas >= np.ceil(t * img.shape[0] * img.shape[1])).sum() < nonempty.sum()


def test_preprocess_and_grid():
    assert resized_shape(480, 640) == (768, 1024) and resized_shape(100, 30) == (1024, 307)
    x = preprocess(np.full((48, 64, 3), 255, np.uint8))  # [1, 3, 1024, 1024]
    assert x.shape == (1, 3, 1024, 1024) and x.dtype == np.float32
    np.testing.assert_allclose(x[0, :, 0, 0], (255 - np.array([123.675, 116.28, 103.53])) / [58.395, 57.12, 57.375],
                               rtol=1e-5)
    assert (x[0, :, 768:] == 0).all() and (x[0, :, :767, :1023] != 0).all()
    g = point_grid(4)
    assert g.shape == (16, 2) and np.allclose(g[0], [0.125, 0.125]) and np.allclose(g[-1], [0.875, 0.875])


def test_stability_score_known_value():
    # A 10x10 logit map: 4 pixels above +1, 16 above -1 (threshold 0, offset 1) -> 4 / 16.
    logits = np.full((10, 10), -5.0)
    logits[2:6, 2:6] = 0.5
    logits[3:5, 3:5] = 2.0
    assert stability_score(logits) == pytest.approx(0.25)
    assert stability_score(logits, threshold=0.0, offset=0.4) == pytest.approx(1.0)  # 16 / 16
    assert stability_score(np.full((1, 2, 4, 4), -9.0)).tolist() == [[0.0, 0.0]]  # empty: 0, not NaN


def test_nms_on_hand_made_masks():
    m = np.zeros((4, 20, 20), bool)
    m[0, 0:10, 0:10] = True    # 100 px
    m[1, 0:10, 0:9] = True     # 90 px inside m0: IoU 0.9
    m[2, 0:10, 0:5] = True     # 50 px inside m0: IoU 0.5
    m[3, 12:20, 12:20] = True  # disjoint
    scores = np.array([0.5, 0.9, 0.8, 0.1])
    assert mask_nms(m, scores, 0.7).tolist() == [1, 2, 3]       # m0 duplicates the better m1
    assert mask_nms(m, scores, 0.4).tolist() == [1, 3]          # m2 vs m1: 50 / 90 > 0.4
    assert mask_nms(m, scores, 0.7, max_keep=2).tolist() == [1, 2]
    assert mask_boxes(m).tolist() == [[0, 0, 9, 9], [0, 0, 8, 9], [0, 0, 4, 9], [12, 12, 19, 19]]
    assert box_nms(mask_boxes(m), scores, 0.7).tolist() == [1, 2, 3]
    # Box NMS alone misses what mask NMS sees: an L shape and the filled square share a box, not their pixels.
    L = np.zeros((2, 10, 10), bool)
    L[0, :, 0] = L[0, 9, :] = True
    L[1] = True
    assert box_nms(mask_boxes(L), np.array([1.0, 0.5]), 0.7).tolist() == [0]
    assert mask_nms(L, np.array([1.0, 0.5]), 0.7).tolist() == [0, 1]


def test_records_to_masks_levels():
    def rec(area, iou, pt):
        seg = np.zeros((10, 10), bool)
        seg.flat[:area] = True
        return {"segmentation": seg, "area": area, "predicted_iou": iou, "stability_score": 0.97,
                "point_coords": [pt]}

    recs = [rec(30, 0.9, [1, 1]), rec(5, 0.95, [1, 1]), rec(60, 1.02, [1, 1]), rec(80, 0.9, [5, 5])]
    out = records_to_masks(recs)
    assert [m.score for m in out] == [1.0, 0.95, 0.9, 0.9]
    assert [(int(m.mask.sum()), m.level) for m in out] == [(60, 2), (5, 0), (30, 1), (80, 2)]
    assert records_to_masks([]) == []


def test_errors(sam_files, tmp_path):
    with pytest.raises(BackendError, match="encoder file not found: .*nope.onnx"):
        make_mask_generator("sam_onnx", encoder_path=str(tmp_path / "nope.onnx"),
                            decoder_path=str(sam_files / "decoder.onnx"))
    with pytest.raises(BackendError, match="decoder file not found"):
        SamOnnxGenerator(str(sam_files / "encoder.onnx"), str(tmp_path / "dec.onnx"))
    with pytest.raises(BackendError, match="lacks inputs"):  # the encoder is not a decoder
        SamOnnxGenerator(str(sam_files / "encoder.onnx"), str(sam_files / "encoder.onnx"))
    gen = SamOnnxGenerator(str(sam_files / "encoder.onnx"), str(sam_files / "decoder.onnx"), points_per_side=2)
    with pytest.raises(ValueError, match="rgb must be uint8"):
        gen.generate(np.zeros((8, 8, 3), np.float32))
    with pytest.raises(ValueError, match="rgb must be uint8"):
        gen.generate(np.zeros((8, 8), np.uint8))
    missing = "segment_anything" if importlib.util.find_spec("segment_anything") is None else "checkpoint"
    with pytest.raises(BackendError, match=missing):
        make_mask_generator("sam", checkpoint=str(tmp_path / "sam_vit_h.pth"))
    with pytest.raises(BackendError, match="mobile_sam|checkpoint"):
        make_mask_generator("sam", checkpoint=str(tmp_path / "mobile_sam.pt"), model_type="vit_t")
