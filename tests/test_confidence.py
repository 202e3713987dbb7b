"""Calibrated confidence and abstention: the metrics rg eval reports, the stored model, and answers
on the session scene that carry their evidence and abstain below the threshold with the best guess."""
import json
import math

import numpy as np
import pytest

from rg_core.eval.grounding import auroc, calibration, expected_calibration_error, risk_coverage
from rg_core.report.plots import calibration_png
from rg_core.grounding.confidence import FEATURES, ConfidenceModel, describe, load_model, model_path


def test_auroc_matches_the_rank_definition():
    rng = np.random.default_rng(0)
    y = rng.random(200) < 0.4
    s = rng.normal(size=200) + y                     # right answers score higher on average
    pairs = [(a > b) + 0.5 * (a == b) for a in s[y] for b in s[~y]]
    assert auroc(s, y) == pytest.approx(float(np.mean(pairs)), abs=1e-9)
    assert auroc(np.r_[1.0, 0.0], np.r_[True, False]) == 1.0
    assert auroc(np.r_[0.5, 0.5], np.r_[True, False]) == 0.5      # ties count half
    assert math.isnan(auroc(np.r_[0.2, 0.3], np.r_[True, True]))  # one class only


def test_expected_calibration_error():
    assert expected_calibration_error(np.r_[1.0, 1.0], np.r_[1, 0]) == pytest.approx(0.5)
    p = np.repeat([0.25, 0.75], 4)
    y = np.r_[1, 0, 0, 0, 1, 1, 1, 0]                  # each bin right as often as it says
    assert expected_calibration_error(p, y) == pytest.approx(0.0)


def test_risk_coverage_orders_by_confidence():
    rc = risk_coverage(np.r_[0.9, 0.1, 0.5], np.r_[True, False, False])
    assert rc["coverage"] == pytest.approx([1 / 3, 2 / 3, 1.0], abs=1e-4)
    assert rc["risk"] == pytest.approx([0.0, 0.5, 2 / 3], abs=1e-4)


def test_calibration_block_counts_wrong_answers_returned_as_success(tmp_path):
    qs = [{"kind": "explicit", "confidence": c, "right": r, "success": s}
          for c, r, s in ((0.9, True, True), (0.8, False, True), (0.2, False, False), (0.3, True, False))]
    c = calibration(qs)["all"]
    assert c["answers"] == 4 and c["right"] == 2 and c["abstained"] == 2
    assert c["wrong_success_share"] == 0.25 and c["right_returned_share"] == 0.5
    png = calibration_png(qs, tmp_path / "rc.png", 0.5, "test")
    assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def _model(coef, threshold=0.5):
    F = len(FEATURES)
    return ConfidenceModel("test", "default", list(FEATURES), np.zeros(F), np.ones(F), np.asarray(coef, float), 0.0, threshold)


def test_model_probability_weakest_and_missing_values():
    coef = np.zeros(len(FEATURES))
    names = list(FEATURES)
    coef[names.index("name_margin")] = 2.0
    coef[names.index("view_agreement")] = 1.0
    m = _model(coef)
    lo = m.probability({"name_margin": -1.0, "view_agreement": 0.0})
    hi = m.probability({"name_margin": 1.0, "view_agreement": 0.0})
    assert 0.0 < lo < 0.5 < hi < 1.0
    # far outside the fit's range the feature counts as 3 spreads (no overflow, no extrapolated certainty)
    assert m.probability({"name_margin": 1e9}) == m.probability({"name_margin": 3.0}) == pytest.approx(1 / (1 + np.exp(-6)))
    assert m.probability({"view_agreement": float("nan")}) == 0.5            # missing = the fit's mean
    assert m.weakest({"name_margin": -1.0, "view_agreement": -0.2}) == ["name_margin", "view_agreement"]
    back = ConfidenceModel.from_json(json.loads(json.dumps(m.to_json())))
    assert back.probability({"name_margin": 0.3}) == pytest.approx(m.probability({"name_margin": 0.3}))
    bad = m.to_json()
    bad["features"] = bad["features"][:-1] + ["a feature this code does not measure"]
    with pytest.raises(ValueError, match="refit"):
        ConfidenceModel.from_json(bad)


def test_the_offline_preset_has_a_fitted_model():
    m = load_model("offline")
    assert m is not None, f"missing {model_path('offline')}: python benchmarks/bench_confidence.py --fit"
    assert 0.0 < m.threshold < 1.0 and np.all(m.std > 0) and np.isfinite(m.coef).all()
    assert "seed" in m.fitted_on and m.metrics["auroc"] > 0.5
    assert load_model("no-such-preset") is None


def test_one_model_per_supervision_source_and_the_map_keeps_its_source(grounder):
    from rg_core.perception.supervision import SupervisionSet

    d, o = load_model("offline", "default"), load_model("offline", "oracle")
    assert d.supervision == "default" and o.supervision == "oracle" and not np.allclose(d.coef, o.coef)
    assert load_model("offline", "something-else").supervision == "default"   # unknown source: the default one
    sset = grounder.mapper.supervision                             # the session map: ground-truth masks
    assert sset.source == "oracle"
    assert SupervisionSet.from_state_dict(sset.state_dict()).source == "oracle"
    old = sset.state_dict()
    del old["source"]                                              # a map saved before sources were kept
    assert SupervisionSet.from_state_dict(old).source == "default"
    r = grounder.ground(grounder.scene_names[0], mode="explicit")
    assert r.confidence == pytest.approx(o.probability(r.evidence)) != pytest.approx(d.probability(r.evidence))


def test_describe_gives_figures():
    ev = {"relevancy_peak": 0.483, "relevancy_z": 1.0, "background_median": 0.47, "background_spread": 0.01,
          "view_agreement": float("nan"), "views_seen": 0.0, "name_margin": -0.12}
    text = describe(ev, ["relevancy_z", "view_agreement", "name_margin"])
    assert "0.483 against the map's 0.470 +- 0.010" in text and "no other view" in text and "-0.12" in text


def test_answers_carry_evidence_and_abstain_below_the_threshold(grounder, synth_scene):
    name = synth_scene.objects[0].name
    r = grounder.ground(name, mode="explicit")
    assert r.objects and set(r.evidence) >= set(FEATURES), r.evidence
    assert all(math.isfinite(v) for k, v in r.evidence.items() if k != "view_agreement")
    assert 0.0 <= r.confidence <= 1.0 and r.objects[0].confidence == pytest.approx(r.confidence)
    assert "confidence" in r.timings and "evidence" in r.to_json()
    grounder.gcfg.min_confidence = 1.0          # nothing is that sure: abstain, keep the best guess
    try:
        a = grounder.ground(name, mode="explicit")
    finally:
        grounder.gcfg.min_confidence = -1.0
    assert not a.success and a.message.startswith(f"not sure the answer is {name!r}") and "best guess" in a.message
    assert a.objects and np.array_equal(a.objects[0].gaussian_ids, r.objects[0].gaussian_ids)
    assert "not sure" in a.explanation and a.confidence == pytest.approx(r.confidence)
    kf = next(k for k in grounder.mapper.keyframes if k.index == a.reference_view)
    amodal, _ = grounder.masks(a, kf.K, kf.cam_to_world, *kf.size)   # the best guess renders (rg eval scores it)
    assert amodal.any()
    grounder.gcfg.min_confidence = 0.0           # never abstain
    try:
        assert grounder.ground(name, mode="explicit").success
    finally:
        grounder.gcfg.min_confidence = -1.0


def test_evidence_of_names_and_of_the_group_in_other_views(grounder, synth_scene):
    names = list(dict.fromkeys(list(grounder.scene_names) + list(grounder.gcfg.vocabulary)))
    name = names[0]
    r = grounder.ground(name, mode="explicit")
    ev = r.evidence
    t = grounder.encode(names)                                       # [n, D] unit rows
    assert ev["name_distinctness"] == pytest.approx(1.0 - float((t[1:] @ t[0]).max()), abs=1e-5)
    # the group's own masks in other views name it: its margin is a similarity difference
    assert ev["views_seen"] >= 1 and -2.0 <= ev["group_name_margin"] <= 2.0
    # measured from the top 1 % of the rest of the map, not from its median
    assert math.isfinite(ev["relevancy_contrast"]) and ev["relevancy_contrast"] < ev["group_relevancy_z"]
    saved = grounder.scene_names
    grounder.scene_names = []                                        # none declared: the whole vocabulary
    try:
        grounder.cache.clear()
        vocab = [n for n in grounder.vocabulary() if n != name]
        whole = grounder.ground(name, mode="explicit").evidence["name_distinctness"]
        assert whole == pytest.approx(1.0 - float((grounder.encode(vocab) @ grounder.encode([name])[0]).max()), abs=1e-5)
    finally:
        grounder.scene_names = saved
        grounder.cache.clear()


def test_eval_reports_confidence_per_query(grounder, synth_scene):
    from rg_core.eval.grounding import evaluate_queries

    ev = evaluate_queries(grounder, synth_scene, implicit_per_object=0)
    qs = ev["queries"]
    assert len(qs) == len({q["query"] for q in qs}) >= 3
    for q in qs:
        assert {"confidence", "right", "miou_visible", "evidence", "success"} <= set(q)
        assert q["right"] == (q["target"] == q["object"] and q["miou_visible"] >= 50.0)
    c = ev["confidence"]
    assert c["all"]["answers"] == len(qs) and len(c["risk_coverage"]["coverage"]) == len(qs)


def _bench_confidence():
    import importlib
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    return importlib.import_module("bench_confidence")


def test_regularisation_is_chosen_out_of_scene():
    """Pure-noise features: the out-of-scene loss is lowest for the strongest L2 (the base rate);
    one clean feature: a weaker one wins. The chosen strength is the grid's lowest loss."""
    bc = _bench_confidence()
    rng = np.random.default_rng(0)
    scenes = np.repeat(np.arange(6), 40)
    y = rng.random(len(scenes)) < 0.3
    noise = rng.normal(size=(len(scenes), 5))
    c, loss, p = bc.choose_c(noise, y, scenes)
    assert c == min(bc.C_GRID) and loss[c] == min(loss.values()), loss
    assert p.shape == y.shape and ((p > 0) & (p < 1)).all()
    signal = np.column_stack([np.where(y, 1.0, -1.0) + 0.3 * rng.normal(size=len(y)), noise])
    c, loss, p = bc.choose_c(signal, y, scenes)
    assert c > min(bc.C_GRID) and loss[c] == min(loss.values()) and loss[c] < 0.3, loss
    assert auroc(p, y) > 0.95       # each scene scored by a model that never saw it


def test_fit_reads_its_threshold_from_out_of_scene_probabilities():
    bc = _bench_confidence()
    rng = np.random.default_rng(2)
    qs = []
    for i in range(240):
        right = bool(rng.random() < 0.3)
        ev = {k: float(rng.normal()) for k in FEATURES}
        ev["view_agreement"] = (1.0 if right else 0.0) + 0.8 * float(rng.normal())
        qs.append({"scene": f"s{i % 6}", "object": f"o{i}", "kind": "explicit", "answered": True,
                   "supervision": "default", "right": right, "evidence": ev})
    m = bc.fit(qs, "test", "default", "six made-up scenes")
    assert m.features == list(FEATURES) and m.metrics["auroc"] > 0.75
    X = np.array([[q["evidence"][k] for k in FEATURES] for q in qs])
    y = np.array([q["right"] for q in qs])
    _, _, p = bc.choose_c(X, y, np.array([q["scene"] for q in qs]))
    assert ((p >= m.threshold) & ~y).mean() <= bc.MAX_WRONG                 # out of scene: at most 8 %
    assert m.threshold == 0.0 or ((p >= m.threshold - 0.01) & ~y).mean() > bc.MAX_WRONG   # and the lowest such


def test_auroc_interval_resamples_objects():
    bc = _bench_confidence()
    sep = [{"scene": "s", "object": f"o{i}", "right": i % 2 == 0, "confidence": 0.9 if i % 2 == 0 else 0.1}
           for i in range(10)]
    assert bc.auroc_interval(sep) == [1.0, 1.0]
    rng = np.random.default_rng(1)
    mixed = [{"scene": "s", "object": f"o{i}", "right": bool(rng.random() < 0.5), "confidence": float(rng.random())}
             for i in range(40)]
    lo, hi = bc.auroc_interval(mixed)
    assert 0.0 <= lo < auroc(np.array([q["confidence"] for q in mixed]), np.array([q["right"] for q in mixed])) < hi <= 1.0
