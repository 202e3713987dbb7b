"""Embedders: crops, the ONNX CLIP backend through its real loading path (a small random model the
test builds and exports), and the packaged offline default."""
import json

import numpy as np
import pytest
import torch

from rg_core.perception.embed import OnnxClipEmbedder, make_embedder, mask_crop
from rg_core.perception.base import BackendError


def test_mask_crop_masks_background_and_pads_square():
    rgb = np.full((40, 60, 3), 200, np.uint8)
    m = np.zeros((40, 60), bool)
    m[10:20, 5:45] = True
    c = mask_crop(rgb, m, margin=0.0)
    assert c.shape == (40, 40, 3)
    assert c[15:25].any() and not c[:15].any() and not c[25:].any()  # padded rows are black
    with pytest.raises(ValueError, match="need at least 16"):
        mask_crop(rgb, np.zeros((40, 60), bool))
    with pytest.raises(ValueError, match="does not match image"):
        mask_crop(rgb, m[:10])


class TinyImage(torch.nn.Module):
    def __init__(self, dim=16):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, 5, stride=4)
        self.fc = torch.nn.Linear(8, dim)

    def forward(self, pixel_values):
        return self.fc(torch.relu(self.conv(pixel_values)).mean((2, 3)))


class TinyText(torch.nn.Module):
    def __init__(self, vocab=64, dim=16):
        super().__init__()
        self.emb = torch.nn.Embedding(vocab, 12)
        self.fc = torch.nn.Linear(12, dim)

    def forward(self, input_ids, attention_mask):
        m = attention_mask.unsqueeze(-1).float()
        return self.fc((self.emb(input_ids) * m).sum(1) / m.sum(1).clamp(min=1.0))


def _tokenizer_files(d):
    """A minimal CLIP BPE vocabulary: single characters, end-of-word forms, special tokens."""
    chars = "abcdefghijklmnopqrstuvwxyz"
    tokens = list(chars) + [c + "</w>" for c in chars] + ["<|startoftext|>", "<|endoftext|>"]
    (d / "vocab.json").write_text(json.dumps({t: i for i, t in enumerate(tokens)}))
    (d / "merges.txt").write_text("#version: 0.2\n")
    return len(tokens)


@pytest.fixture(scope="module")
def onnx_clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("clip")
    vocab = _tokenizer_files(d)
    torch.manual_seed(0)
    img, txt = TinyImage().eval(), TinyText(vocab).eval()
    torch.onnx.export(img, (torch.randn(2, 3, 32, 32),), str(d / "image.onnx"), input_names=["pixel_values"],
                      output_names=["embeds"], dynamic_axes={"pixel_values": {0: "n"}, "embeds": {0: "n"}}, dynamo=False)
    ids = torch.zeros(2, 8, dtype=torch.long)
    torch.onnx.export(txt, (ids, torch.ones_like(ids)), str(d / "text.onnx"), input_names=["input_ids", "attention_mask"],
                      output_names=["embeds"], dynamic_axes={"input_ids": {0: "n"}, "attention_mask": {0: "n"},
                                                              "embeds": {0: "n"}}, dynamo=False)
    emb = make_embedder("onnx_clip", image_model=str(d / "image.onnx"), text_model=str(d / "text.onnx"),
                        tokenizer_dir=str(d), image_size=32, context_length=8)
    return emb, img, txt, d


def test_onnx_clip_matches_the_exported_model(onnx_clip):
    emb, img, txt, _ = onnx_clip
    rng = np.random.default_rng(0)
    crops = [rng.integers(1, 255, (h, w, 3), dtype=np.uint8) for h, w in ((40, 40), (17, 33), (64, 64))]
    e = emb.encode_images(crops)
    assert e.shape == (3, 16)
    torch.testing.assert_close(e.norm(dim=-1), torch.ones(3))
    with torch.no_grad():
        ref = torch.nn.functional.normalize(img(torch.from_numpy(emb.preprocess(crops))), dim=-1)
    torch.testing.assert_close(e, ref, atol=1e-5, rtol=1e-4)
    t = emb.encode_texts(["a mug", "lemon", "a very long phrase that is cut to the context"])
    assert t.shape == (3, 16)
    ids, mask = emb.tokenize(["a mug"])
    assert ids.shape == (1, 8) and mask[0, 0] == 1 and ids[0, 0] == emb.tok.convert_tokens_to_ids("<|startoftext|>")
    with torch.no_grad():
        ref_t = torch.nn.functional.normalize(txt(torch.from_numpy(ids), torch.from_numpy(mask)), dim=-1)
    torch.testing.assert_close(t[:1], ref_t, atol=1e-5, rtol=1e-4)


def test_onnx_clip_errors(onnx_clip, tmp_path):
    emb, _, _, d = onnx_clip
    with pytest.raises(BackendError, match="image_model file not found"):
        OnnxClipEmbedder(str(tmp_path / "none.onnx"), str(d / "text.onnx"), str(d))
    with pytest.raises(BackendError, match="tokenizer file not found"):
        OnnxClipEmbedder(str(d / "image.onnx"), str(d / "text.onnx"), str(tmp_path))
    with pytest.raises(ValueError, match="empty crop"):
        emb.encode_images([np.zeros((10, 10, 3), np.uint8)])
    with pytest.raises(ValueError, match="expected uint8"):
        emb.encode_images([np.zeros((10, 10), np.float32)])


def test_conse_offline_default(conse_embedder, synth_scene):
    conse = conse_embedder
    t = conse.encode_texts(["coffee mug", "banana"])
    assert t.shape == (2, conse.dim) and conse.dim == 384
    f = synth_scene.frames[2]
    rgb, vis = f.load_rgb(), f.load_visible_mask()
    crops = [mask_crop(rgb, vis == o.id) for o in synth_scene.objects if (vis == o.id).sum() >= 16]
    e = conse.encode_images(crops)
    assert e.shape == (len(crops), 384) and torch.isfinite(e).all()
    torch.testing.assert_close(e.norm(dim=-1), torch.ones(len(crops)))
    # Class probabilities are a distribution over the 1000 ImageNet classes.
    p = conse.class_probs(crops)
    assert p.shape == (len(crops), 1000) and torch.allclose(p.sum(-1), torch.ones(len(crops)), atol=1e-4)


def test_colour_histogram_names_basic_colours():
    from rg_core.perception.colour_names import COLOUR_TERMS, colour_histogram

    cases = {(230, 20, 20): "red", (255, 128, 0): "orange", (240, 230, 30): "yellow", (20, 180, 40): "green",
             (20, 40, 220): "blue", (128, 0, 200): "purple", (255, 105, 180): "pink", (110, 60, 20): "brown",
             (250, 250, 250): "white", (128, 128, 128): "grey", (10, 10, 10): "black", (200, 0, 30): "red"}
    for rgb, word in cases.items():
        h = colour_histogram(np.array([rgb] * 5, np.uint8))
        assert COLOUR_TERMS[int(h.argmax())] == word and h.max() == 1.0, (rgb, h)
    mixed = colour_histogram(np.array([(20, 40, 220)] * 3 + [(240, 230, 30)], np.uint8))
    assert mixed[COLOUR_TERMS.index("blue")] == 0.75 and abs(mixed.sum() - 1) < 1e-12
    with pytest.raises(ValueError, match="no pixels"):
        colour_histogram(np.zeros((0, 3), np.uint8))
    with pytest.raises(ValueError, match="expected uint8"):
        colour_histogram(np.zeros((4, 3), np.float32))


def test_conse_colour_term_tells_colours_apart(conse_embedder):
    import copy

    conse = conse_embedder
    # The same disc in blue and in yellow on the crop fill: the classifier sees two similar
    # objects; the colour term must pull each towards its own colour word.
    yy, xx = np.mgrid[:64, :64]
    disc = (yy - 32) ** 2 + (xx - 32) ** 2 < 24 ** 2
    crops = []
    for rgb in ((20, 40, 220), (240, 230, 30)):
        c = np.empty((64, 64, 3), np.uint8)
        c[:] = conse.crop_fill
        c[disc] = rgb
        crops.append(c)
    e = conse.encode_images(crops)
    t = conse.encode_texts(["blue cup", "yellow cup"])
    s = e @ t.T
    assert s[0, 0] > s[0, 1] and s[1, 1] > s[1, 0], s
    # Without the colour term the embedding is plain ConSE: the top-k class mixture.
    plain = copy.copy(conse)
    plain.colour_weight = 0.0
    p = conse.class_probs(crops)
    top = p.topk(conse.top_k, dim=-1)
    w = top.values / top.values.sum(-1, keepdim=True)
    expect = torch.nn.functional.normalize((w[..., None] * conse.class_emb[top.indices]).sum(1), dim=-1)
    torch.testing.assert_close(plain.encode_images(crops), expect)
    assert (plain.encode_images(crops) - e).norm(dim=-1).min() > 0.05
    # Mirror averaging (optional): a crop and its mirror image get the same class probabilities.
    mirror = copy.copy(conse)
    mirror.mirror = True
    pm = mirror.class_probs(crops[:1])
    torch.testing.assert_close(mirror.class_probs([crops[0][:, ::-1].copy()]), pm, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(pm, 0.5 * (p[:1] + conse.class_probs([crops[0][:, ::-1].copy()])), atol=1e-5, rtol=1e-4)
    # A crop with no object pixels (all fill) has no colour term: finite, unit, equal to plain.
    blank = np.empty((32, 32, 3), np.uint8)
    blank[:] = conse.crop_fill
    torch.testing.assert_close(conse.encode_images([blank]), plain.encode_images([blank]))
    # Centred colour words: no common "colour" direction that would favour every name holding one.
    torch.testing.assert_close(conse.colour_emb.sum(0), torch.zeros(conse.dim), atol=1e-5, rtol=0)
    # A colour covering less than min_colour of the object adds nothing.
    speck = np.empty((40, 40, 3), np.uint8)
    speck[:] = (128, 128, 128)
    speck[:2, :2] = (20, 40, 220)
    assert conse.colour_term([speck]).abs().max() == 0
    with pytest.raises(ValueError, match="colour_weight"):
        type(conse)(colour_weight=-1.0)
