"""The plain-torch MiniLM against sentence-transformers (the package it replaces on the query path),
and the text embeddings a map stores so that a new process needs no text model for them."""
import pytest
import torch

from rg_core.perception import minilm
from rg_core.perception.embed import MiniLMText

TEXTS = ["coffee mug", "a lemon", "Something to drink HOT tea from, sturdy and ceramic!", "x", "",
         "a very long description " * 60]  # the last is truncated at 256 tokens, as sentence-transformers does


def test_minilm_matches_sentence_transformers():
    st = pytest.importorskip("sentence_transformers")
    folder = minilm.model_folder()
    ref = st.SentenceTransformer(str(folder), device="cpu").encode(TEXTS, convert_to_tensor=True,
                                                                   normalize_embeddings=True).float()
    ours = minilm.MiniLM(folder)(TEXTS)
    assert ours.shape == ref.shape == (len(TEXTS), 384)
    torch.testing.assert_close(ours, ref, atol=2e-6, rtol=0)
    # One at a time (no padding) gives the same rows as a padded batch.
    torch.testing.assert_close(minilm.MiniLM(folder)(TEXTS[:1]), ours[:1], atol=2e-6, rtol=0)


def test_known_texts_skip_the_model():
    enc = MiniLMText()
    assert enc._model is None  # constructing it loads nothing
    fake = torch.nn.functional.normalize(torch.arange(384.0), dim=0)
    minilm.remember({"a stored name": fake})
    try:
        out = enc(["a stored name", "a stored name"])
        assert enc._model is None  # answered from the store
        torch.testing.assert_close(out, torch.stack([fake, fake]))
        new = enc(["something never seen"])
        assert enc._model is not None and new.shape == (1, 384)
        torch.testing.assert_close(new.norm(dim=-1), torch.ones(1))
    finally:
        minilm.KNOWN.pop("a stored name", None)
