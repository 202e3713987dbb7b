"""Grounding queries of a scene: the team's description set (issue 15) as default implicit queries
for named objects, and anyone's own queries in the scene's queries.json format (`rg eval --queries`)."""
from __future__ import annotations

import json
from pathlib import Path

from .images import SceneError
from .scene import Query, SceneObject, _load_json

DESCRIPTIONS = Path(__file__).resolve().parents[1] / "perception" / "data" / "descriptions.json"


def description_categories() -> dict[str, str]:
    """Object name -> category ("food", "toy", ...) of the description set."""
    return {o["name"]: o.get("category", "object") for o in _descriptions().get("objects", [])}


def _descriptions() -> dict:
    return json.loads(DESCRIPTIONS.read_text(encoding="utf-8")) if DESCRIPTIONS.is_file() else {}


def default_queries(objects: list[SceneObject]) -> list[Query]:
    """Explicit query = the object's name; implicit ones = the team's description set (issue 15)
    for that name, in the set's order (none when the set does not cover the object)."""
    desc = {o["name"]: [d["text"] for d in o["descriptions"]] for o in _descriptions().get("objects", [])}
    return [Query(o.id, o.name, desc.get(o.name, [])) for o in objects]


def read_queries(path: str | Path, objects: list[SceneObject]) -> list[Query]:
    """A queries.json file ([{"object_id", "explicit", "implicit": [...]}], as synthetic scenes
    write it; "object": NAME may replace object_id) checked against the scene's objects."""
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, list):
        raise SceneError(f"{path}: expected a JSON list of queries, got {type(data).__name__}")
    by_name = {o.name: o.id for o in objects}
    ids = {o.id for o in objects}
    out = []
    for k, q in enumerate(data):
        where = f"{path}: query {k}"
        if not isinstance(q, dict):
            raise SceneError(f"{where}: expected an object with object_id, explicit, implicit")
        oid = q.get("object_id")
        if oid is None and "object" in q:
            if q["object"] not in by_name:
                raise SceneError(f"{where}: object {q['object']!r} is not in the scene ({sorted(by_name)})")
            oid = by_name[q["object"]]
        if not isinstance(oid, int) or oid not in ids:
            raise SceneError(f"{where}: object_id {oid!r} is not an object of the scene ({sorted(ids)})")
        explicit = q.get("explicit", next(o.name for o in objects if o.id == oid))
        implicit = q.get("implicit", [])
        if isinstance(implicit, str):
            implicit = [implicit]
        if not isinstance(explicit, str) or not all(isinstance(t, str) for t in implicit):
            raise SceneError(f"{where}: explicit must be a string and implicit a list of strings")
        out.append(Query(oid, explicit, list(implicit)))
    if not out:
        raise SceneError(f"{path}: no queries")
    return out
