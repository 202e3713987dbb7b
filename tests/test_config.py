import pytest

from conftest import assert_load_errors
from rg_core.config import ConfigError, RGConfig, config_from_dict, config_to_dict, load_config


def test_defaults_and_example_file_match_schema():
    cfg = load_config("config/rg.example.yaml")
    assert isinstance(cfg, RGConfig)
    assert cfg.synth.ring_radius == (0.38, 0.62)
    assert config_to_dict(cfg) == config_to_dict(RGConfig())  # the example documents the defaults


def test_partial_override_keeps_other_defaults(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("synth:\n  views: 12\n  near: 1\n")
    cfg = load_config(p)
    assert cfg.synth.views == 12 and cfg.synth.near == 1.0 and isinstance(cfg.synth.near, float)
    assert cfg.synth.width == RGConfig().synth.width


@pytest.mark.parametrize("data, key", [
    ({"synth": {"viewz": 3}}, "synth.viewz"),
    ({"sinth": {}}, "sinth"),
    ({"synth": {"views": "ten"}}, "synth.views"),
    ({"synth": {"views": True}}, "synth.views"),
    ({"synth": {"near": "far"}}, "synth.near"),
    ({"synth": {"ring_radius": [0.1]}}, "synth.ring_radius"),
    ({"synth": {"ring_radius": [0.1, "x"]}}, "synth.ring_radius[1]"),
    ({"synth": 5}, "synth"),
    ({"map": {"near": float("nan")}}, "map.near"),
    ({"field": {"seconds": float("inf")}}, "field.seconds"),
    ({"ground": {"outlier_mads": -1.0}}, "ground.outlier_mads"),
])
def test_bad_keys_and_types_name_the_key(data, key):
    with pytest.raises(ConfigError) as info:
        config_from_dict(data)
    assert str(info.value).startswith(key + ":"), str(info.value)


def test_bad_file_errors_name_the_file(tmp_path):
    assert_load_errors(load_config, ConfigError, tmp_path, [
        ("missing.yaml", None, "not found"),
        ("bad.yaml", "synth: [unclosed\n", "bad.yaml: not valid YAML"),
        ("typo.yaml", "demo:\n  seeds: 1\n", r"typo.yaml: demo.seeds: unknown key"),
    ])
