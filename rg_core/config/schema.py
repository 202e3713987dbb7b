"""Validation of the config sections by pydantic: YAML dicts (strict: ints for floats, lists for
tuples, nothing else converted; unknown keys and NaN/inf refused) and sections built in Python
(check_fields). Every error names its key path."""
from __future__ import annotations

import dataclasses
import functools
import json
import typing
from typing import Any


class ConfigError(ValueError):
    """A configuration file or dict does not match the schema; the message names the key."""


def section(cls: type) -> type:
    """A config section: a dataclass that pydantic validates with unknown keys and NaN/inf refused
    (its ConfigDict as a plain dict: pydantic is imported only when a file or dict is validated)."""
    cls.__pydantic_config__ = {"extra": "forbid", "allow_inf_nan": False, "use_attribute_docstrings": True}
    return dataclasses.dataclass(cls)


@functools.cache
def _adapter(cls: type):
    from pydantic import TypeAdapter
    return TypeAdapter(cls)


def _section_at(cls: type, loc: tuple) -> type:
    """The config section a key path leads to, for listing its known keys."""
    for part in loc:
        tp = typing.get_type_hints(cls).get(part)
        if not dataclasses.is_dataclass(tp):
            break
        cls = tp
    return cls


def _message(cls: type, err: dict) -> str:
    """One pydantic error as `key.path: what was wrong, got VALUE`."""
    loc = list(err["loc"])
    if err["type"] == "missing" and loc and isinstance(loc[-1], int):   # a list one value short of a tuple
        loc.pop()
    key = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".") or "top level"
    if err["type"] == "unexpected_keyword_argument":
        parent = typing.get_type_hints(_section_at(cls, tuple(loc[:-1])))
        return f"{key}: unknown key (known keys: {', '.join(sorted(parent))})"
    if err["type"] == "missing":
        return f"{key}: too few values, got {err.get('input')!r}"
    return f"{key}: {err['msg'].replace('Input should be', 'expected')}, got {err.get('input')!r}"


def from_dict(data: dict | None, cls: type) -> Any:
    """Build a config section from a plain dict (None: its defaults), validated by pydantic."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"top level: expected a mapping, got {type(data).__name__}")
    from pydantic import ValidationError
    try:
        return _adapter(cls).validate_json(json.dumps(data, default=str), strict=True)
    except ValidationError as exc:
        raise ConfigError("; ".join(_message(cls, e) for e in exc.errors())) from None


def check_fields(obj: Any) -> None:
    """Validate a section built in Python (no YAML) against its annotations: types, ranges
    (annotated_types) and choices (Literal); ConfigError names each wrong field."""
    from pydantic import ValidationError

    hints, errors = typing.get_type_hints(type(obj), include_extras=True), []
    for f in dataclasses.fields(obj):
        try:
            _field_adapter(hints[f.name]).validate_python(getattr(obj, f.name), strict=True)
        except ValidationError as exc:
            errors += [_message(type(obj), {**e, "loc": (f.name, *e["loc"])}) for e in exc.errors()]
    if errors:
        raise ConfigError("; ".join(errors))


@functools.cache
def _field_adapter(tp: Any):
    from pydantic import ConfigDict, TypeAdapter
    return TypeAdapter(tp, config=ConfigDict(allow_inf_nan=False))
