"""One configuration format: YAML mapped onto typed dataclasses, validated by pydantic.

Defaults live in code: one dataclass per section, in a module per capability (synth, mapping,
field, ground, reason, models); this package re-exports them. A YAML file only overrides what it
names; an unknown key, a value of the wrong type or a NaN is an error that names the full key
path, so a typo in a robot's config fails at start-up instead of being silently ignored.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import yaml

from .constants import CACHE_DIR, MAX_QUERY_CHARS  # noqa: F401 - the package's API
from .field import FieldConfig
from .ground import GroundConfig
from .mapping import MapConfig, PhotoMapConfig
from .models import ModelsConfig
from .reason import ReasonConfig
from .schema import ConfigError, check_fields, from_dict, section  # noqa: F401 - the package's API
from .sfm import SfmConfig
from .synth import DemoConfig, SynthConfig


@section
class RGConfig:
    """Top level of a ReasonGrounder configuration file."""

    synth: SynthConfig = dataclasses.field(default_factory=SynthConfig)
    demo: DemoConfig = dataclasses.field(default_factory=DemoConfig)
    map: MapConfig = dataclasses.field(default_factory=MapConfig)
    photo: PhotoMapConfig = dataclasses.field(default_factory=PhotoMapConfig)
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    ground: GroundConfig = dataclasses.field(default_factory=GroundConfig)
    reason: ReasonConfig = dataclasses.field(default_factory=ReasonConfig)
    models: ModelsConfig = dataclasses.field(default_factory=ModelsConfig)
    sfm: SfmConfig = dataclasses.field(default_factory=SfmConfig)


def config_from_dict(data: dict | None, cls: type = RGConfig) -> Any:
    """A config (RGConfig or one section) from a plain dict, every key and type checked."""
    return from_dict(data, cls)


def load_config(path: str | Path | None = None) -> RGConfig:
    """Load a YAML configuration file (None: all defaults)."""
    if path is None:
        return RGConfig()
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: configuration file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def config_to_dict(cfg: Any) -> dict:
    """Plain-dict view of a config (tuples become lists), e.g. to write YAML or JSON."""

    def plain(v: Any) -> Any:
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        if isinstance(v, list):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return plain(dataclasses.asdict(cfg))
