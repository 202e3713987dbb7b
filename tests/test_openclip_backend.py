"""OpenCLIP embedder: its errors (always), and its real loading path on a tiny random open_clip model
the test configures and saves (only where open_clip and a working torchvision are installed)."""
import importlib.util
import json

import numpy as np
import pytest
import torch

from rg_core.perception.embed import make_embedder
from rg_core.perception.base import BackendError


def _open_clip():
    """open_clip, or skip: it needs torchvision built for the installed torch (the PyPI Linux wheel is a
    CUDA build whose import fails next to CPU torch)."""
    try:
        import open_clip
    except (ImportError, RuntimeError) as e:  # RuntimeError: a torchvision built for another torch
        pytest.skip(f"open_clip does not import: {type(e).__name__}: {e}")
    return open_clip


def test_open_clip_missing_files_and_packages(tmp_path):
    with pytest.raises(BackendError, match="checkpoint file not found: .*none.pt") as err:
        make_embedder("open_clip", checkpoint=str(tmp_path / "none.pt"))
    for pkg in ("open_clip", "torchvision"):
        if importlib.util.find_spec(pkg) is None:
            assert f"'{pkg}' package is not installed" in str(err.value)
    with pytest.raises(BackendError, match="model config file not found"):
        make_embedder("open_clip", checkpoint=str(tmp_path / "none.pt"), config_path=str(tmp_path / "Tiny.json"))


TINY = {"embed_dim": 32,
        "vision_cfg": {"image_size": 32, "layers": 2, "width": 64, "head_width": 32, "patch_size": 16},
        "text_cfg": {"context_length": 16, "vocab_size": 49408, "width": 64, "heads": 2, "layers": 2}}


def test_open_clip_tiny_model(tmp_path):
    open_clip = _open_clip()
    cfg = tmp_path / "TinyRGCLIP.json"
    cfg.write_text(json.dumps(TINY))
    open_clip.add_model_config(cfg)
    torch.manual_seed(0)
    ref = open_clip.create_model("TinyRGCLIP").eval()
    torch.save(ref.state_dict(), tmp_path / "tiny.pt")

    emb = make_embedder("open_clip", checkpoint=str(tmp_path / "tiny.pt"), config_path=str(cfg))
    assert emb.dim == 32 and emb.size == 32
    rng = np.random.default_rng(0)
    crops = [rng.integers(1, 255, (h, w, 3), dtype=np.uint8) for h, w in ((40, 40), (17, 33), (64, 64))]
    e = emb.encode_images(crops)
    t = emb.encode_texts(["a mug", "lemon"])
    assert e.shape == (3, 32) and t.shape == (2, 32) and e.dtype == t.dtype == torch.float32
    torch.testing.assert_close(e.norm(dim=-1), torch.ones(3))
    torch.testing.assert_close(t.norm(dim=-1), torch.ones(2))
    torch.testing.assert_close(emb.encode_images(crops), e)  # deterministic
    # The checkpoint was loaded: the reference model gives the same embeddings.
    with torch.no_grad():
        torch.testing.assert_close(e, ref.encode_image(emb.preprocess(crops), normalize=True), atol=1e-5, rtol=1e-4)
        tok = open_clip.get_tokenizer("TinyRGCLIP")(["a mug", "lemon"])  # [2, 16]
        torch.testing.assert_close(t, ref.encode_text(tok, normalize=True), atol=1e-5, rtol=1e-4)
    assert emb.encode_images([]).shape == (0, 32) and emb.encode_texts([]).shape == (0, 32)
    with pytest.raises(ValueError, match="empty crop"):
        emb.encode_images([np.zeros((10, 10, 3), np.uint8)])
