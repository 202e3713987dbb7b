"""`rg`'s options generated from the config dataclasses (rg_core/cli/config_args.py): one per field
of the sections a subcommand reads, defaults < --config FILE < flag, bad values refused by the
schema with the option's name. The commands are stubbed: what reaches them is the merged config."""
import dataclasses
import json
import typing

import pytest

import rg_core.cli as cli
from rg_core.cli import config_args, evaluation, grounding, mapping, reporting, synthesis
from rg_core.config import RGConfig, config_to_dict

SECTIONS = {"synth": {"synth"}, "map": {"map", "photo", "field", "models"}, "ground": {"ground", "reason", "models"},
            "graph": {"ground", "reason", "models"}, "eval": {"map", "photo", "field", "ground", "reason", "models"},
            "report": {"map", "photo", "field", "ground", "reason", "models"}, "models": {"models"}, "sfm": {"sfm"},
            "demo": {"demo", "synth", "map", "field", "ground", "reason", "models"}}
COMMANDS = {"synth": (synthesis, "cmd_synth"), "map": (mapping, "cmd_map"), "ground": (grounding, "cmd_ground"),
            "eval": (evaluation, "cmd_eval"), "demo": (reporting, "cmd_demo")}


def subparsers() -> dict:
    return cli.build_parser()._subparsers._group_actions[0].choices


@pytest.mark.parametrize("command", sorted(SECTIONS))
def test_every_field_of_each_section_it_reads_is_an_option(command):
    p = subparsers()[command]
    options = {s for a in p._actions for s in a.option_strings}
    generated = {s.split(".")[0][2:] for s in options if "." in s}
    assert generated == SECTIONS[command]
    hints = {name: typing.get_type_hints(cls) for name, cls in config_args.sections().items()}
    for name in SECTIONS[command]:
        for f in dataclasses.fields(config_args.sections()[name]):
            assert f"--{name}.{f.name}" in options, (command, name, f.name)
            if hints[name][f.name] is bool:
                assert f"--{name}.no_{f.name}" in options
    text = p.format_help()
    for name in SECTIONS[command]:
        assert f"config section {name} (--{name}.FIELD)" in text   # one group per section


def test_help_is_the_fields_docstring():
    """The help comes from the attribute docstrings, as pydantic reads them for the schema."""
    from pydantic import TypeAdapter

    schema = TypeAdapter(RGConfig).json_schema()["$defs"]
    for name, cls in config_args.sections().items():
        props = schema[cls.__name__]["properties"]
        docs = config_args.attribute_docs(cls)
        assert docs, name
        for key, prop in props.items():
            assert docs.get(key, "") == " ".join(prop.get("description", "").split()), (name, key)
    text = subparsers()["map"].format_help()
    assert "Working image width: frames are resized to it" in " ".join(text.split())


def run(monkeypatch, capfd, command, *argv, config=None):
    """`rg [--config FILE] COMMAND ... --json` with COMMAND's work replaced by returning its config."""
    module, name = COMMANDS[command]
    monkeypatch.setattr(module, name, lambda args, cfg: {"cfg": config_to_dict(cfg)})
    pre = ["--config", str(config)] if config else []
    code = cli.main([*pre, command, *argv, "--json"])
    out = json.loads(capfd.readouterr().out.strip().splitlines()[-1])
    return code, out.get("cfg", out)


def test_a_flag_reaches_the_commands_config(monkeypatch, capfd):
    code, cfg = run(monkeypatch, capfd, "map", "scene", "--out", "m.rgmap", "--map.width", "123",
                    "--field.steps", "50", "--models.views_per_object", "0")
    assert code == 0
    assert (cfg["map"]["width"], cfg["field"]["steps"], cfg["models"]["views_per_object"]) == (123, 50, 0)
    defaults = config_to_dict(RGConfig())
    assert {k: v for k, v in cfg["map"].items() if k != "width"} == {k: v for k, v in defaults["map"].items()
                                                                     if k != "width"}
    code, cfg = run(monkeypatch, capfd, "ground", "m.rgmap", "q", "--ground.min_confidence", "0.3",
                    "--reason.top_k", "5", "--ground.cluster_eps", "1")
    assert code == 0 and (cfg["ground"]["min_confidence"], cfg["reason"]["top_k"]) == (0.3, 5)
    assert cfg["ground"]["cluster_eps"] == 1.0 and isinstance(cfg["ground"]["cluster_eps"], float)


def test_precedence_defaults_then_config_file_then_flag(monkeypatch, capfd, tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("map:\n  width: 200\n  iters_per_keyframe: 7\nsynth:\n  views: 9\n")
    code, cfg = run(monkeypatch, capfd, "map", "scene", "--out", "m.rgmap", "--map.width", "123", config=f)
    assert code == 0
    assert cfg["map"]["width"] == 123                      # the flag over the file
    assert cfg["map"]["iters_per_keyframe"] == 7           # the file over the default
    assert cfg["synth"]["views"] == 9                      # a section the command does not expose: the file's
    assert cfg["map"]["window"] == RGConfig().map.window   # neither: the default
    code, cfg = run(monkeypatch, capfd, "map", "scene", "--out", "m.rgmap", config=f)
    assert code == 0 and cfg["map"]["width"] == 200


@pytest.mark.parametrize("argv, message", [
    (("map", "s", "--out", "m", "--map.width", "abc"), "--map.width: expected a valid integer, got 'abc'"),
    (("map", "s", "--out", "m", "--field.steps", "-5"), "--field.steps: expected greater than or equal to 0"),
    (("map", "s", "--out", "m", "--map.iters_per_keyframe", "1.5"), "--map.iters_per_keyframe: expected a valid integer"),
    (("map", "s", "--out", "m", "--field.seconds", "nan"), "--field.seconds: expected a finite number"),
    (("synth", "s", "--synth.layout", "hall"), "--synth.layout: expected 'table' or 'room', got 'hall'"),
    (("synth", "s", "--synth.ring_radius", "0.3", "far"), "--synth.ring_radius[1]: expected a valid number"),
    (("ground", "m", "q", "--min-confidence", "2"), "--ground.min_confidence: expected less than or equal to 1"),
])
def test_a_bad_value_is_an_error_naming_the_option(monkeypatch, capfd, argv, message):
    code, out = run(monkeypatch, capfd, *argv)
    assert code == 2 and set(out) == {"error"} and message in out["error"], out
    code = cli.main(list(argv))   # without --json: the message on stderr
    assert code == 2 and f"rg {argv[0]}: error: {message}" in capfd.readouterr().err


def test_bool_tuple_and_list_fields(monkeypatch, capfd, tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("ground:\n  grow_groups: false\n")
    code, cfg = run(monkeypatch, capfd, "ground", "m", "q", "--ground.grow_groups", "--reason.llm_scorer",
                    "--ground.no_anchor_support", "--ground.vocabulary", "mug", "tea pot", config=f)
    assert code == 0
    assert (cfg["ground"]["grow_groups"], cfg["ground"]["anchor_support"], cfg["reason"]["llm_scorer"]) == \
        (True, False, True)
    assert cfg["ground"]["vocabulary"] == ["mug", "tea pot"]
    code, cfg = run(monkeypatch, capfd, "ground", "m", "q", "--ground.no_grow_groups", "--ground.vocabulary")
    assert code == 0 and cfg["ground"]["grow_groups"] is False and cfg["ground"]["vocabulary"] == []
    code, cfg = run(monkeypatch, capfd, "synth", "s", "--synth.ring_radius", "0.3", "1")
    assert code == 0 and cfg["synth"]["ring_radius"] == [0.3, 1.0]
    with pytest.raises(SystemExit) as info:   # a tuple of two takes two values
        cli.build_parser().parse_args(["synth", "s", "--synth.ring_radius", "0.3"])
    assert info.value.code == 2


def test_documented_flags_are_aliases_of_the_fields(monkeypatch, capfd):
    code, cfg = run(monkeypatch, capfd, "synth", "s", "--views", "3", "--size", "64x48", "--objects", "2", "--seed", "5",
                    "--workers", "1", "--same-category", "1", "--layout", "room", "--tables", "2")
    s = cfg["synth"]
    assert code == 0 and (s["views"], s["width"], s["height"], s["objects"], s["seed"], s["workers"],
                          s["same_category"], s["layout"], s["tables"]) == (3, 64, 48, 2, 5, 1, 1, "room", 2)
    code, cfg = run(monkeypatch, capfd, "map", "s", "--out", "m", "--width", "80", "--iters-per-keyframe", "2",
                    "--max-gaussians", "5000", "--preset", "paper_cpu")
    assert code == 0 and (cfg["map"]["width"], cfg["map"]["iters_per_keyframe"], cfg["map"]["max_gaussians"],
                          cfg["models"]["preset"]) == (80, 2, 5000, "paper_cpu")
    code, cfg = run(monkeypatch, capfd, "ground", "m", "q", "--min-confidence", "0", "--backend", "openai",
                    "--preset", "paper")
    assert code == 0 and (cfg["ground"]["min_confidence"], cfg["reason"]["backend"], cfg["models"]["preset"]) == \
        (0.0, "openai", "paper")
    code, cfg = run(monkeypatch, capfd, "eval", "s", "--field-steps", "7", "--preset", "paper")
    assert code == 0 and (cfg["field"]["steps"], cfg["models"]["preset"]) == (7, "paper")
    # one destination: the last of alias and option wins; an empty --preset keeps the config's, as before
    code, cfg = run(monkeypatch, capfd, "map", "s", "--out", "m", "--width", "80", "--map.width", "90")
    assert cfg["map"]["width"] == 90
    code, cfg = run(monkeypatch, capfd, "map", "s", "--out", "m", "--map.width", "90", "--width", "80")
    assert cfg["map"]["width"] == 80
    code, cfg = run(monkeypatch, capfd, "ground", "m", "q", "--preset", "paper", "--preset", "")
    assert cfg["models"]["preset"] == RGConfig().models.preset
    with pytest.raises(SystemExit):   # the alias keeps its own check
        cli.build_parser().parse_args(["map", "s", "--out", "m", "--width", "0"])


def test_a_backend_on_the_command_line_is_known_as_given():
    """rg ground / rg eval then skip the preset's LVLM (apply_reasoner), whichever spelling named it."""
    parse = cli.build_parser().parse_args
    assert config_args.was_given(parse(["ground", "m", "q", "--backend", "text"]), "reason.backend")
    assert config_args.was_given(parse(["eval", "s", "--reason.backend", "text"]), "reason.backend")
    assert not config_args.was_given(parse(["ground", "m", "q", "--reason.top_k", "2"]), "reason.backend")
