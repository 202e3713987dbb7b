"""The reasoning benchmark's description set (rg_core/perception/data/descriptions.json, issue 15):
schema, the counts the issue asks for, coverage of every name a scene can hold, and that no
description gives its answer away by naming its own object."""
from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import pytest

import rg_core
from rg_core.io.ycb import ycb_class_name
from rg_core.synth.catalogue import PYBULLET_OBJECTS, SHARED_OBJECTS

from conftest import RGBD

DATA = Path(rg_core.__file__).parent / "perception" / "data" / "descriptions.json"
STYLES = {"function", "attribute", "context"}
CATEGORIES = {"kitchen", "food", "household", "office", "tool", "bathroom", "toy"}
# The 21 YCB-Video classes (a fixed property of the data set, as in its classes.txt).
YCB_CLASSES = (
    "002_master_chef_can", "003_cracker_box", "004_sugar_box", "005_tomato_soup_can", "006_mustard_bottle",
    "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box", "010_potted_meat_can", "011_banana",
    "019_pitcher_base", "021_bleach_cleanser", "024_bowl", "025_mug", "035_power_drill", "036_wood_block",
    "037_scissors", "040_large_marker", "051_large_clamp", "052_extra_large_clamp", "061_foam_brick")


@pytest.fixture(scope="module")
def data() -> dict:
    return json.loads(DATA.read_text(encoding="utf-8"))


def _names_itself(name: str, text: str) -> bool:
    return re.search(r"\b" + re.escape(name) + r"\b", text, flags=re.IGNORECASE) is not None


def test_schema(data):
    assert set(data) == {"version", "about", "objects", "absent"}
    assert data["version"] == 1 and isinstance(data["about"], str) and "2026-11-24" in data["about"]
    for o in data["objects"]:
        assert set(o) == {"name", "category", "descriptions"}, o.get("name")
        assert isinstance(o["name"], str) and o["name"] == o["name"].strip().lower() and o["name"], o
        assert o["category"] in CATEGORIES, (o["name"], o["category"])
        for d in o["descriptions"]:
            assert set(d) == {"style", "text"} and d["style"] in STYLES, (o["name"], d)
            assert isinstance(d["text"], str) and d["text"] == d["text"].strip() and len(d["text"]) >= 8, d
    for d in data["absent"]:
        assert set(d) == {"style", "text"} and d["style"] in STYLES, d
        assert isinstance(d["text"], str) and d["text"] == d["text"].strip() and len(d["text"]) >= 8, d


def test_counts(data):
    objects = data["objects"]
    assert len(objects) >= 70
    for o in objects:
        styles = Counter(d["style"] for d in o["descriptions"])
        assert len(o["descriptions"]) >= 5 and set(styles) == STYLES, (o["name"], dict(styles))
    assert sum(len(o["descriptions"]) for o in objects) >= 380
    assert len(data["absent"]) >= 50 and {d["style"] for d in data["absent"]} == STYLES


def test_unique_names_and_texts(data):
    names = [o["name"] for o in data["objects"]]
    assert not [n for n, c in Counter(names).items() if c > 1]
    texts = [d["text"].lower() for o in data["objects"] for d in o["descriptions"]]
    texts += [d["text"].lower() for d in data["absent"]]
    assert not [t for t, c in Counter(texts).items() if c > 1]


def test_covers_catalogue_and_ycb_names(data):
    names = {o["name"] for o in data["objects"]}
    catalogue = {e.name for e in SHARED_OBJECTS + PYBULLET_OBJECTS}
    assert not catalogue - names, sorted(catalogue - names)
    ycb = {ycb_class_name(c) for c in YCB_CLASSES}
    assert len(ycb) == 21 and not ycb - names, sorted(ycb - names)
    shipped = RGBD / "ycb_video_3" / "classes.txt"
    if shipped.is_file():  # the shared photos' own class list says the same
        assert {ycb_class_name(c) for c in shipped.read_text().splitlines() if c.strip()} == ycb


def test_no_description_names_its_object(data):
    offenders = [(o["name"], d["text"]) for o in data["objects"] for d in o["descriptions"]
                 if _names_itself(o["name"], d["text"])]
    assert not offenders
    names = [o["name"] for o in data["objects"]]
    absent_named = [(n, d["text"]) for d in data["absent"] for n in names if _names_itself(n, d["text"])]
    assert not absent_named


def test_not_copied_from_the_tuned_catalogue(data):
    tuned = {t.lower() for e in SHARED_OBJECTS + PYBULLET_OBJECTS for t in e.implicit}
    assert not [d["text"] for o in data["objects"] for d in o["descriptions"] if d["text"].lower() in tuned]


def test_name_check_can_fail():
    assert _names_itself("blue cup", "the Blue Cup on the left")
    assert not _names_itself("blue cup", "the blue cupboard") and not _names_itself("pen", "a pencil")


def test_shipped_as_package_data():
    setup_py = (Path(__file__).resolve().parents[1] / "setup.py").read_text()
    assert '"perception/data/*.json"' in setup_py and DATA.is_file()
