"""Relational queries over the scene graph: the rule parser, and answers on the session scene with
oracle supervision checked against the ground-truth object centres."""
import numpy as np
import pytest

from rg_core.grounding.relations import Relational, colour_term, parse


@pytest.mark.parametrize("query, want", [
    ("how many apples are there?", Relational("apple", count=True)),
    ("How many red cups", Relational("cup", "red", count=True)),
    ("the biggest object", Relational("", superlative="biggest")),
    ("the smallest cup", Relational("cup", superlative="smallest")),
    ("the object nearest to me", Relational("", superlative="nearest_camera")),
    ("the closest cup to the camera", Relational("cup", superlative="nearest_camera")),
    ("the object closest to the lemon", Relational("", relation="near", anchors=["lemon"])),
    ("the mug next to the laptop", Relational("mug", relation="near", anchors=["laptop"])),
    ("the thing between the apple and the banana", Relational("", relation="between", anchors=["apple", "banana"])),
    ("the blue cup left of the bowl", Relational("cup", "blue", "left", ["bowl"])),
    ("the cup to the right of the salt and pepper", Relational("cup", relation="right", anchors=["salt and pepper"])),
    ("the red cup", Relational("cup", "red")),
])
def test_parse(query, want):
    assert parse(query) == want


@pytest.mark.parametrize("query", ["coffee mug", "a sturdy vessel for hot beverages", "something to drink hot tea from",
                                   "the fruit that fell on Newton's head", "a round red fruit that keeps the doctor away",
                                   "blue", "the thing between the apple"])
def test_plain_names_and_descriptions_are_not_relational(query):
    assert parse(query) is None


def test_colour_terms():
    px = lambda rgb: np.tile(np.array(rgb, np.uint8), (50, 1))   # noqa: E731
    assert colour_term(px([200, 30, 30])) == "red" and colour_term(px([40, 60, 200])) == "blue"
    assert colour_term(px([250, 250, 250])) == "white" and colour_term(px([0, 0, 80])) == "dark blue"
    assert colour_term(px([150, 200, 255])) == "light blue"


def _centres(scene):
    return {o.name: (np.asarray(o.aabb_min) + np.asarray(o.aabb_max)) / 2 for o in scene.objects}


def test_graph_holds_each_object_once(grounder, synth_scene):
    objs = grounder.scene_graph()
    gt = _centres(synth_scene)
    found = {o.name: o for o in objs if o.name in gt}
    assert len(found) >= len(gt) - 1, [o.to_json() for o in objs]
    for name, o in found.items():   # the object's box holds its true centre (2 cm slack: a tiny scene)
        assert np.linalg.norm(o.centre - gt[name]) < 0.05, (name, o.centre, gt[name])
        assert o.colour and o.to_json()["names"][0][0] == name
    assert grounder.scene_graph() is objs    # cached until the map changes


def test_relations_match_the_ground_truth(grounder, synth_scene):
    gt = _centres(synth_scene)
    names = sorted(gt)
    checked = 0
    for anchor in names:
        d = sorted((float(np.linalg.norm(c - gt[anchor])), n) for n, c in gt.items() if n != anchor)
        if d[1][0] - d[0][0] < 0.03:      # ambiguous by the stated margin: not asked
            continue
        r = grounder.ground(f"the object closest to the {anchor}")
        assert r.success and r.target == d[0][1], (anchor, d[:2], r.message)
        assert f"near '{anchor}'" in r.explanation and "next nearest" in r.explanation
        assert "graph" in r.timings and len(r.objects) == 1
        checked += 1
    assert checked >= 2
    r = grounder.ground(f"how many {names[0]}s are there?")
    assert r.success and len(r.objects) == 1 and r.message.startswith(f"1 {names[0]!r}")


def test_missing_anchor_and_absent_target_say_so(grounder):
    r = grounder.ground("the object next to the giraffe")
    assert not r.success and "no 'giraffe' in the map to relate to" in r.message and "objects:" in r.message
    r = grounder.ground("how many unicorns are there")
    assert not r.success and "no 'unicorn' in the map" in r.message


def test_plain_names_skip_the_graph(grounder, synth_scene):
    r = grounder.ground(synth_scene.objects[0].name)
    assert "graph" not in r.timings and "reference_view" in r.timings


def test_names_match_plurals_compounds_and_categories():
    from rg_core.grounding.relations import SceneObject, _match
    from rg_core.grounding.result import GroundedObject

    def obj(name, colour="red"):
        z = np.zeros(3)
        return SceneObject([(name, 0.9)], GroundedObject(np.zeros(1, np.int64), np.zeros((1, 3), np.float32),
                                                         np.zeros((1, 3), np.uint8), z, z, z, np.eye(3), z), colour)

    objs = [obj("banana", "yellow"), obj("plum", "purple"), obj("blue cup", "blue"), obj("hammer", "grey"),
            obj("phillips screwdriver", "yellow")]
    names = lambda found: sorted(o.name for o in found)   # noqa: E731
    assert names(_match(objs, "fruits")) == ["banana", "plum"]
    assert names(_match(objs, "cup")) == ["blue cup"]
    assert names(_match(objs, "tool")) == ["hammer", "phillips screwdriver"]
    assert names(_match(objs, "tool", "yellow")) == ["phillips screwdriver"]
    assert names(_match(objs, "giraffe")) == [] and len(_match(objs, "")) == 5


def test_rg_eval_scores_relational_queries_as_implicit_queries_of_their_target(grounder, synth_scene):
    """`rg eval --queries FILE`: a relational query listed as an implicit query of its target object
    takes the graph path and is scored against that object."""
    import copy

    from rg_core.eval.grounding import evaluate_queries
    from rg_core.io.scene import Query

    gt = _centres(synth_scene)
    by_name = {o.name: o for o in synth_scene.objects}
    anchor, target = None, None
    for a in sorted(gt):
        d = sorted((float(np.linalg.norm(c - gt[a])), n) for n, c in gt.items() if n != a)
        if d[1][0] - d[0][0] >= 0.03:
            anchor, target = a, d[0][1]
            break
    assert anchor, "the session scene has an unambiguous nearest neighbour"
    scene = copy.copy(synth_scene)
    scene.queries = [Query(by_name[target].id, target, [f"the object closest to the {anchor}"])]
    ev = evaluate_queries(grounder, scene, implicit_per_object=1)
    imp = [q for q in ev["queries"] if q["kind"] == "implicit"]
    assert len(imp) == 1 and imp[0]["target"] == target and ev["implicit"]["target_accuracy"] == 100.0, imp
    assert ev["implicit"]["miou_visible"] > 0.0
