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


def test_one_model_per_process_and_load_ahead():
    """Every encoder of the packaged folder shares one loaded model; load() loads it before any text,
    so a node's first query does not pay for it; the grounder loads its reasoner's and its own."""
    from rg_core.grounding.pipeline import Grounder
    from rg_core.perception.text_cache import inner_encoder

    a, b = MiniLMText(), MiniLMText()
    a.load()
    assert a._model is not None and b._model is None
    assert b.model is a.model and minilm.MiniLM.shared(minilm.model_folder()) is a.model
    assert not any(p.is_meta for p in a.model.parameters())   # every weight came from the checkpoint

    class Stub:   # the map and field are not used to load models
        supervision = None

    g = Grounder(Stub(), None, text_encoder=MiniLMText())
    assert g.load_models() is g
    assert inner_encoder(g.text_model())._model is a.model
    assert inner_encoder(g.reasoner.text)._model is a.model
