"""Relational queries over the scene graph: the rule parser, and answers on the session scene with
oracle supervision checked against the ground-truth object centres."""
from types import SimpleNamespace

import numpy as np
import pytest

from rg_core.grounding.phrases import Relational, parse
from rg_core.perception.colour_names import colour_term


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
    ("how many cups are on the table", Relational("cup", relation="on", anchors=["table"], count=True)),
    ("count the cups", Relational("cup", count=True)),
    ("show me all the fruit next to the bowl", Relational("fruit", relation="near", anchors=["bowl"], every=True)),
    ("the second cup from the left", Relational("cup", ordinal=2, side="left")),
    ("the last screwdriver from the right", Relational("screwdriver", ordinal=-1, side="right")),
    ("the leftmost object", Relational("", ordinal=1, side="left")),
    ("whatever is on the right", Relational("", ordinal=1, side="right")),
    ("the cup on the left of the bowl", Relational("cup", relation="left", anchors=["bowl"])),
    ("the apple on top of the box", Relational("apple", relation="on", anchors=["box"])),
    ("the ball under the table", Relational("ball", relation="under", anchors=["table"])),
    ("the thing above the bowl", Relational("", relation="above", anchors=["bowl"])),
    ("the tallest thing", Relational("", superlative="tallest")),
    ("the highest object", Relational("", superlative="highest")),
    ("where is the mug that is next to the laptop?", Relational("mug", relation="near", anchors=["laptop"])),
])
def test_parse(query, want):
    assert parse(query) == want


@pytest.mark.parametrize("query", ["coffee mug", "a sturdy vessel for hot beverages", "something to drink hot tea from",
                                   "the fruit that fell on Newton's head", "a round red fruit that keeps the doctor away",
                                   "blue", "the thing between the apple", "a lamp that turns on at night",
                                   "something to write on", "what you put on a bed to sleep on"])
def test_plain_names_and_descriptions_are_not_relational(query):
    assert parse(query) is None


def test_colour_terms():
    px = lambda rgb: np.tile(np.array(rgb, np.uint8), (50, 1))   # noqa: E731
    assert colour_term(px([200, 30, 30])) == "red" and colour_term(px([40, 60, 200])) == "blue"
    assert colour_term(px([250, 250, 250])) == "white" and colour_term(px([0, 0, 80])) == "dark blue"
    assert colour_term(px([150, 200, 255])) == "light blue"


def test_colour_term_in_cielab_names_focal_colours_and_ignores_shading():
    focal = {"red": (220, 30, 30), "orange": (245, 130, 20), "yellow": (245, 220, 30), "green": (40, 170, 60),
             "blue": (30, 80, 210), "purple": (130, 50, 160), "pink": (245, 150, 190), "brown": (110, 70, 40),
             "white": (240, 240, 240), "grey": (128, 128, 128), "black": (20, 20, 20), "dark blue": (0, 0, 128)}
    for word, rgb in focal.items():
        assert colour_term(np.array([rgb], np.uint8)) == word, (word, colour_term(np.array([rgb], np.uint8)))
    # a white bowl, 60 % of it in shadow, is still white; a grey one lit on a rim is grey; a black
    # screwdriver seen with 30 % of the wooden table at its rim is black
    bowl = np.array([[245, 245, 245]] * 40 + [[160, 160, 160]] * 60, np.uint8)
    assert colour_term(bowl) == "white"
    assert colour_term(np.array([[130, 130, 130]] * 90 + [[250, 250, 250]] * 10, np.uint8)) == "grey"
    assert colour_term(np.array([[25, 25, 28]] * 70 + [[200, 160, 110]] * 30, np.uint8)) == "black"
    # a red mug with a white label is red; extremes of the range are still named
    assert colour_term(np.array([[200, 20, 30]] * 60 + [[250, 250, 250]] * 40, np.uint8)) == "red"
    assert colour_term(np.zeros((1, 3), np.uint8)) == "black"
    assert colour_term(np.full((1, 3), 255.0)) == "white"
    # shading decides nothing on its own: an orange cup (LCh hue 47) 60 % in shade, whose shaded
    # pixels alone read brown, is orange; a black-and-grey tool whose pixels split three ways
    # between black, grey and white by how the light falls on it takes the median lightness
    lit, shade = np.array([[215, 95, 50]] * 40, np.uint8), np.array([[120, 52, 28]] * 60, np.uint8)
    assert colour_term(shade) == "brown" and colour_term(np.concatenate([lit, shade])) == "orange"
    tool = np.array([[20, 20, 20]] * 35 + [[100, 100, 100]] * 30 + [[200, 200, 200]] * 25 + [[200, 120, 30]] * 10,
                    np.uint8)
    assert colour_term(tool) == "grey"
    # a wooden spoon: brown lit or not
    assert colour_term(np.array([[110, 70, 40]] * 50 + [[70, 45, 25]] * 50, np.uint8)) == "brown"
    for bad in (np.zeros((0, 3), np.uint8), np.zeros((3, 4), np.uint8), np.array([[np.nan, 0, 0]])):
        with pytest.raises(ValueError, match="colour_term"):
            colour_term(bad)


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


def test_an_objects_colour_comes_from_every_keyframe_that_sees_it(grounder, synth_scene):
    from rg_core.grounding.appearance import observed_pixels

    m = grounder.mapper
    o = next(o for o in grounder.scene_graph() if o.name in _centres(synth_scene))
    pts = m.gaussians.means.detach().numpy()[o.obj.gaussian_ids]
    per_kf = [len(observed_pixels(SimpleNamespace(keyframes=[kf]), pts)) for kf in m.keyframes]   # one at a time
    assert sum(n > 0 for n in per_kf) > 4, per_kf            # seen from more sides than the old four
    assert len(observed_pixels(m, pts)) == sum(per_kf)
    assert len(observed_pixels(m, pts, max_pixels=50)) <= 50 and len(observed_pixels(m, pts[:0])) == 0


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


def obj(name, colour="red", lo=(0, 0, 0), hi=(0, 0, 0), conf=0.9):
    """A graph object filling the box lo..hi (map frame, z up) with points."""
    from rg_core.grounding.relations import SceneObject
    from rg_core.grounding.result import GroundedObject

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pts = (lo + np.random.default_rng(0).random((200, 3)) * (hi - lo)).astype(np.float32)
    return SceneObject([(name, conf)], GroundedObject(np.arange(200), pts, np.zeros((200, 3), np.uint8), lo, hi,
                                                      (lo + hi) / 2, np.eye(3), hi - lo), colour)


def test_names_match_plurals_compounds_and_categories():
    from rg_core.grounding.relations import _match

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


def _camera():
    """Looking along +y from (0, -2, 0.5), z up: +x is right in the image."""
    from rg_core.geometry.conventions import look_at

    return look_at([0.0, -2.0, 0.5], [0.0, 0.0, 0.5])


def _ask(query, objs, max_results=1):
    from rg_core.grounding.relations import answer

    return answer(parse(query), objs, _camera(), "the test camera", max_results, query, up=np.array([0.0, 0.0, 1.0]))


def test_support_ordinals_heights_and_all_over_a_built_graph():
    table = obj("table", "brown", (-0.6, -0.4, 0.0), (0.6, 0.4, 0.75))
    cups = [obj(f"{c} cup", c, (x, 0.0, 0.75), (x + 0.08, 0.08, 0.85)) for c, x in (("red", -0.4), ("blue", 0.0),
                                                                                  ("green", 0.3))]
    box = obj("toy box", "yellow", (0.9, 0.0, 0.0), (1.2, 0.3, 0.3))                 # on the floor, not the table
    ball = obj("ball", "orange", (-0.1, -0.1, 0.0), (0.05, 0.05, 0.15))              # under the table
    lamp = obj("lamp", "white", (0.0, 0.0, 1.6), (0.2, 0.2, 1.7))                    # hanging above it
    objs = [table, *cups, box, ball, lamp]
    r = _ask("how many cups are on the table", objs)
    assert r.success and len(r.objects) == 3 and r.message.startswith("3 'cup' on 'table'")
    r = _ask("the second cup from the left", objs)
    assert r.target == "blue cup" and "2nd of 3 from the left, seen from the test camera" in r.explanation
    assert _ask("the last cup from the left", objs).target == "green cup"
    assert _ask("the cup on the right", objs).target == "green cup"
    r = _ask("the fifth cup from the left", objs)
    assert not r.success and "only 3 'cup'" in r.message
    assert _ask("the ball under the table", objs).success and _ask("the object under the table", objs).target == "ball"
    assert _ask("the thing above the table", objs).target == "lamp"
    r = _ask("the toy box on the table", objs)
    assert not r.success and r.message == "no 'toy box' on 'table'"
    assert _ask("the tallest object", objs).target == "table" and _ask("the highest object", objs).target == "lamp"
    assert _ask("the lowest object", objs).target == "ball"
    r = _ask("all the cups", objs, max_results=1)
    assert len(r.objects) == 3, "all: every match, whatever max_results"
    r = _ask("the cup left of the green cup", objs, max_results=2)       # ranked: the nearest first
    assert [id(o) for o in r.objects] == [id(cups[1].obj), id(cups[0].obj)]
    assert len(_ask("the biggest cup", objs, max_results=5).objects) == 3
    r = _ask("the cup next to the ball", objs)
    assert r.target == "blue cup" and "next nearest" in r.explanation
    r = _ask("how many things are near the ball", objs)
    assert {o.name for o in objs if any(o.obj is x for x in r.objects)} == {"table"}   # the cup is 0.6 m up
    two = objs + [obj("table", "white", (3, 3, 0), (4, 4, 0.7), conf=0.5)]
    r = _ask("the cup on the table", two)
    assert r.success and "2 'table' in the map: relating to the most certain (0.90)" in r.explanation


def test_what_an_anchor_rests_on_is_not_beside_it():
    """A table top's map can hold the table as an object (under a wrong name, as offline names go):
    'the object closest to the scissors' is then not the table the scissors lie on."""
    table = obj("lamp", "brown", (-0.6, -0.4, 0.70), (0.6, 0.4, 0.75))       # the table, misnamed
    scissors = obj("scissors", "black", (0.0, 0.0, 0.75), (0.15, 0.06, 0.76))
    cup = obj("orange cup", "orange", (0.3, 0.0, 0.75), (0.38, 0.08, 0.85))
    spoon = obj("spoon", "grey", (-0.4, 0.2, 0.75), (-0.2, 0.3, 0.76))
    peach = obj("peach", "orange", (-0.35, 0.22, 0.755), (-0.3, 0.27, 0.8))    # sunk into the spoon's box
    objs = [table, scissors, cup, spoon, peach]
    for q in ("the object closest to the scissors", "the object right of the scissors",
              "the thing next to the scissors", "what is between the scissors and the orange cup"):
        r = _ask(q, objs)
        if "between" in q:
            assert r.target != "lamp", (q, r.message)
            continue
        assert r.success and r.target == "orange cup", (q, r.message)
        assert "'lamp' left out: 'scissors' rests on it" in r.explanation, r.explanation
    assert _ask("the object under the scissors", objs).target == "lamp"     # asked for: it is what lies under
    r = _ask("the object closest to the peach", objs)                       # one thing on it: not a surface
    assert r.target == "spoon" and "'spoon' left out" not in r.explanation, r.explanation
    assert _ask("the object closest to the scissors", objs[:3]).target == "lamp"   # holding two: not a surface
    r = _ask("how many things are near the lamp", objs)                     # the table as the anchor: unchanged
    assert r.success and len(r.objects) >= 1


def test_on_the_table_without_a_table_in_the_map_means_on_no_other_object():
    """A table top's map rarely holds the table as an object: "on the table" then counts what rests
    on a surface rather than on another object, and says so; another missing anchor is still an error."""
    plate = obj("plate", "white", (0.0, 0.0, 0.75), (0.2, 0.2, 0.77))
    cups = [obj("red cup", "red", (0.5, 0.0, 0.75), (0.58, 0.08, 0.85)),
            obj("blue cup", "blue", (0.05, 0.05, 0.77), (0.13, 0.13, 0.87))]    # the blue cup stands on the plate
    objs = [plate, *cups]
    r = _ask("how many cups are on the table?", objs)
    assert r.success and len(r.objects) == 1 and r.objects[0] is cups[0].obj, r.message
    assert r.message.startswith("1 'cup' on the table") and "read as resting on a surface" in r.explanation
    assert _ask("the cup on the desk", objs).target == "red cup"
    assert _ask("how many cups are on the plate", objs).objects == [cups[1].obj]
    r = _ask("how many cups are on the giraffe", objs)
    assert not r.success and "no 'giraffe' in the map to relate to" in r.message
    r = _ask("the cup next to the table", objs)      # only "on" reads a missing support as a surface
    assert not r.success and "no 'table' in the map to relate to" in r.message
    # a support named only as an object's runner-up (the oracle map of seed 419: clamp 0.99, table 0.59)
    clamp = obj("clamp", "black", (0.3, 0.3, 0.75), (0.4, 0.4, 0.8))
    clamp.names.append(("table", 0.59))
    r = _ask("how many cups are on the table?", objs + [clamp])
    assert r.success and len(r.objects) == 1 and "read as resting on a surface" in r.explanation, r.explanation


def test_relational_descriptions_of_absent_things_take_the_usual_path(grounder):
    r = grounder.ground("small metal scoop on a handle")       # a description of a spoon, not a relation
    assert "graph" not in r.timings
    r = grounder.ground("the object on top of the giraffe")   # any object: the graph, which lacks the anchor
    assert not r.success and "no 'giraffe' in the map to relate to" in r.message
    long = "the cup next to the " + "very " * 400 + "big bowl"
    r = grounder.ground(long)
    assert not r.success and "characters" in r.message


def test_names_with_articles_and_lead_ins_take_the_usual_path(grounder, synth_scene):
    from rg_core.grounding.phrases import bare_name

    vocab = ["blue cup", "orange", "coffee mug"]
    assert bare_name("Pick up the blue cup, please!", vocab) == "blue cup" and bare_name("the orange", vocab) == "orange"
    assert bare_name("all the coffee mugs", vocab) is None and bare_name("the red cup", vocab) is None
    name = synth_scene.objects[0].name
    plain, polite = grounder.ground(name), grounder.ground(f"show me the {name}, please")
    assert "graph" not in polite.timings and polite.target == plain.target and polite.success == plain.success
    assert polite.query == f"show me the {name}, please"           # the result says what was asked
    assert np.array_equal(polite.objects[0].gaussian_ids, plain.objects[0].gaussian_ids)


def test_an_exact_name_beats_its_category_as_anchor():
    objs = [obj("bowl", "white", (0, 0, 0), (0.1, 0.1, 0.05), conf=0.6),
            obj("cartoon bowl", "grey", (1, 0, 0), (1.1, 0.1, 0.05), conf=0.99),
            obj("lemon", "yellow", (0.15, 0, 0), (0.2, 0.05, 0.05)),
            obj("marker", "black", (1.15, 0, 0), (1.2, 0.05, 0.05))]
    r = _ask("the object closest to the bowl", objs)
    assert r.target == "lemon" and "relating to the most certain" not in r.explanation, r.explanation
    assert _ask("the object closest to the cartoon bowl", objs).target == "marker"
    cups = [obj("orange cup", "yellow", (0, 0, 0), (0.1, 0.1, 0.1), conf=0.5),
            obj("yellow cup", "orange", (1, 0, 0), (1.1, 0.1, 0.1), conf=0.9)]
    assert _ask("the orange cup", cups).target == "orange cup"     # the name says it, ahead of a measured colour


def _fields(**over):
    base = dict(target="", colour="", relation="", anchors=[], superlative="", ordinal=0, side="", count=False,
                every=False)
    return {**base, **over}


@pytest.mark.parametrize("data, want", [
    (_fields(target="Cups", colour="red", count=True), Relational("cup", "red", count=True)),
    (_fields(target="the mug", relation="near", anchors=["the laptop"]), Relational("mug", relation="near", anchors=["laptop"])),
    (_fields(target="object", relation="between", anchors=["apple", "bananas"]),
     Relational("", relation="between", anchors=["apple", "banana"])),
    (_fields(target="screwdriver", ordinal=2, side="left"), Relational("screwdriver", ordinal=2, side="left")),
    (_fields(superlative="biggest"), Relational("", superlative="biggest")),
    (_fields(target="coffee mug"), None),                        # a plain name: the usual path
    ({"target": "cup", "colour": "blue"}, Relational("cup", "blue")),   # missing keys: their empty values
])
def test_llm_parser_answers_become_the_rule_parsers_fields(data, want):
    from rg_core.grounding.phrases import from_fields

    assert from_fields(data) == want


@pytest.mark.parametrize("data, message", [
    ([], "expected a JSON object"),
    (_fields(target="cup", relation="beside", anchors=["bowl"]), "relation 'beside' is not one of"),
    (_fields(target="cup", relation="between", anchors=["bowl"]), "takes 2 anchor(s), got 1"),
    (_fields(target="cup", relation="near", anchors=[]), "takes 1 anchor(s), got 0"),
    (_fields(target="cup", anchors=["bowl"]), "relation 'none' takes 0 anchor(s)"),
    (_fields(target="cup", ordinal=2), "ordinal 2 and side '' go together"),
    (_fields(target="cup", ordinal=99, side="left"), "outside -1..20"),
    (_fields(target="cup", count="yes"), "count is str 'yes', expected boolean"),
    (_fields(target="cup", ordinal=True, side="left"), "ordinal is bool"),
    (_fields(target="cup", colour="magenta"), "colour 'magenta' is not one of"),
    ({**_fields(target="cup"), "mood": "happy"}, "unknown key(s) ['mood']"),
    (_fields(target="cup", relation="near", anchors=["  "]), "anchors must be object names"),
    (_fields(target="cup", relation="near", anchors=[3]), "anchors must be object names"),
])
def test_llm_parser_answers_that_break_the_schema_are_refused(data, message):
    from rg_core.grounding.phrases import from_fields

    with pytest.raises(ValueError) as exc:
        from_fields(data)
    assert message in str(exc.value)


@pytest.mark.parametrize("query, fields, message", [
    ("the red cups next to the laptops", _fields(target="cup", colour="red", relation="near", anchors=["laptop"]), None),
    ("how many apples are there", _fields(target="apple", count=True), None),
    ("the largest thing", _fields(superlative="biggest"), None),             # enum words need not be the query's
    # what SmolLM2-135M answered for these (bench_llm_parse): its prompt's example, not the query
    ("the object closest to the lemon", _fields(target="cup", colour="red", relation="between", anchors=["red", "orange"],
                                                superlative="biggest", ordinal=2, side="left"), "target 'cup' is not in the query"),
    ("the object between the bowl and the fork", _fields(relation="between", anchors=["bowl", "spoon"]),
     "anchor 'spoon' is not in the query"),
    ("the cup left of the bowl", _fields(target="cup", colour="blue", relation="left", anchors=["bowl"]),
     "colour 'blue' is not in the query"),
])
def test_llm_parses_naming_what_the_query_never_said_are_refused(query, fields, message):
    from rg_core.grounding.phrases import _check_words_in, from_fields

    rq = from_fields(fields)
    if message is None:
        _check_words_in(rq, query)
    else:
        with pytest.raises(ValueError, match=message):
            _check_words_in(rq, query)


def test_llm_parse_option_falls_back_to_the_rules_when_the_model_is_unreachable(oracle_field, synth_scene, grounder):
    """reason.llm_parse with an OpenAI endpoint nobody serves: the rule parser answers, the same
    objects as without the option, and the explanation says why."""
    import socket

    from rg_core.config import RGConfig
    from rg_core.grounding.pipeline import Grounder
    from rg_core.perception.reasoning import TextReasoner
    from rg_core.perception.reasoning.llm import OpenAIChatReasoner

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    field, embed = oracle_field
    cfg = RGConfig()
    cfg.reason.llm_parse = True
    llm = OpenAIChatReasoner(base_url=f"http://127.0.0.1:{port}/v1", timeout_s=5, fallback=TextReasoner())
    g = Grounder(field.mapper, field, cfg, reasoner=llm, text_encoder=embed, scene_names=[o.name for o in synth_scene.objects])
    query = f"the object closest to the {synth_scene.objects[0].name}"
    r, plain = g.ground(query), grounder.ground(query)
    assert r.success == plain.success and [o.gaussian_ids.tolist() for o in r.objects] == \
        [o.gaussian_ids.tolist() for o in plain.objects]
    assert "openai parse unusable (connection failed" in r.explanation and "parsed by rules" in r.explanation, r.explanation
    assert "parse unusable" not in plain.explanation


def test_a_misnamed_table_plane_is_not_one_of_the_things_on_it():
    """Offline names can call the table's plane a thing ('clock'): holding three objects, it is a
    surface, so 'the biggest object' is among the things on it and 'on the table' counts what rests
    on it. A support named as one ('table') stays an object (the test above)."""
    plane = obj("clock", "brown", (-0.6, -0.4, 0.70), (0.6, 0.4, 0.75))
    things = [obj("phillips screwdriver", "yellow", (-0.4, 0.0, 0.75), (-0.2, 0.05, 0.79)),
              obj("flat screwdriver", "red", (0.0, 0.0, 0.75), (0.12, 0.03, 0.77)),
              obj("knife", "grey", (0.3, 0.0, 0.75), (0.5, 0.02, 0.76))]
    objs = [plane, *things]
    r = _ask("the biggest object", objs)
    assert r.success and r.target == "phillips screwdriver", r.message
    assert "'clock' left out" in r.explanation
    r = _ask("how many screwdrivers are there on the table", objs)
    assert r.success and len(r.objects) == 2, r.message
    # with two things only on it, it is no surface: still the biggest
    assert _ask("the biggest object", [plane, *things[:2]]).target == "clock"


def test_generated_view_queries_ask_only_what_has_an_answer():
    """The ground-truth generator: 'the first cup from the left' only when every cup is in front of
    the camera (a bearing behind it has no left and right), and 'nearest' answers only when the
    runner-up is farther by the answerer's tie share, not just 3 cm (at 2.6 m: 13 cm)."""
    from rg_core.eval.relational import margin, queries

    assert margin(0.2) == pytest.approx(0.03) and margin(2.6) == pytest.approx(0.13)

    def scene(ys):
        objs = [SimpleNamespace(id=i + 1, name=n, aabb_min=np.array([x, y, 0.0]), aabb_max=np.array([x + 0.08, y + 0.08, 0.1]))
                for i, (n, x, y) in enumerate(zip(["red cup", "blue cup", "green cup"], [-0.5, 0.0, 0.5], ys))]
        return SimpleNamespace(objects=objs)

    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    ordinals = lambda ys: [q for q in queries(scene(ys), np.random.default_rng(0), {}, _camera(), K)   # noqa: E731
                           if q["kind"] == "ordinal"]
    assert ordinals([0.0, 0.0, 0.0])
    assert not ordinals([0.0, 0.0, -3.0]), "the green cup lies behind the camera"
