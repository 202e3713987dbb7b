"""Command-line options generated from the config dataclasses (what tyro does for nerfstudio, in a
page of argparse): `--<section>.<field>` for every field of the sections a subcommand reads, typed
from the annotation, its help the field's docstring. The values given override `--config FILE`,
which overrides the defaults in code, and go through the schema's validation like a YAML file's."""
from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import sys
import typing
from typing import Any

from ..config import ConfigError, RGConfig, config_from_dict, config_to_dict

PREFIX = "config:"   # the dest of a generated option: "config:map.width"


@functools.cache
def sections() -> dict[str, type]:
    """Section name -> its dataclass, as RGConfig lists them."""
    hints = typing.get_type_hints(RGConfig)
    return {f.name: hints[f.name] for f in dataclasses.fields(RGConfig)}


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


def _bare(tp: Any) -> Any:
    """The type without its Annotated constraints (ranges stay the schema's to check)."""
    return typing.get_args(tp)[0] if typing.get_origin(tp) is typing.Annotated else tp


@functools.cache
def attribute_docs(cls: type) -> dict[str, str]:
    """Field name -> the string literal under it in the class body (the field's docstring)."""
    try:
        tree = ast.parse(inspect.getsource(sys.modules[cls.__module__]))
    except (OSError, TypeError, KeyError):   # no source (a frozen install): options without help
        return {}
    body = next((n.body for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls.__name__), [])
    return {a.target.id: " ".join(b.value.value.split()) for a, b in zip(body, body[1:])
            if isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr)
            and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str)}


class _Switch(argparse.Action):
    """A bool field: `--s.f` sets it, `--s.no_f` clears it."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, option_string == self.option_strings[0])


class _ShortUsage(argparse.HelpFormatter):
    """The usage line names the generated options as one `[--{map,field}.FIELD VALUE]` (their help
    lists each)."""

    def _format_usage(self, usage, actions, groups, prefix):
        names = list(dict.fromkeys(a.dest[len(PREFIX):].partition(".")[0] for a in actions
                                   if a.dest.startswith(PREFIX)))
        kept = [a for a in actions if not a.dest.startswith(PREFIX)]
        if names:
            label = names[0] if len(names) == 1 else "{" + ",".join(names) + "}"
            kept.append(argparse.Action([f"--{label}.FIELD"], "config", metavar="VALUE"))
        return super()._format_usage(usage, kept, groups, prefix)


def add_sections(parser: argparse.ArgumentParser, names: tuple[str, ...]) -> None:
    """One option per field of each named section, an argument group per section."""
    parser.formatter_class = _ShortUsage
    for name in names:
        cls = sections()[name]
        doc = " ".join((cls.__doc__ or "").split())
        group = parser.add_argument_group(f"config section {name} (--{name}.FIELD)", doc.replace("%", "%%"))
        defaults, docs = cls(), attribute_docs(cls)
        for f in dataclasses.fields(cls):
            default = getattr(defaults, f.name)
            text = f"{docs.get(f.name, '')} (default: {default!r})".lstrip().replace("%", "%%")
            option, tp = f"--{name}.{f.name}", _bare(_hints(cls)[f.name])
            kwargs = dict(dest=f"{PREFIX}{name}.{f.name}", default=argparse.SUPPRESS, help=text)
            if tp is bool:
                group.add_argument(option, f"--{name}.no_{f.name}", action=_Switch, **kwargs)
            elif typing.get_origin(tp) in (tuple, list):
                args = typing.get_args(tp)
                fixed = typing.get_origin(tp) is tuple and Ellipsis not in args
                group.add_argument(option, nargs=len(args) if fixed else "*",
                                   metavar=tuple(_metavar(a) for a in args) if fixed else _metavar(args[0]), **kwargs)
            else:
                group.add_argument(option, metavar=_metavar(tp), **kwargs)


def _metavar(tp: Any) -> str:
    if typing.get_origin(tp) is typing.Literal:
        return "{" + ",".join(str(v) for v in typing.get_args(tp)) + "}"
    return getattr(tp, "__name__", "VALUE").upper()


class _Alias(argparse.Action):
    """A hand-written flag that sets config fields: its (typed) value, spread over several fields
    when it is a tuple (`--size WxH`); an empty string leaves them as they were."""

    def __init__(self, option_strings, dest, keys=(), **kwargs):
        super().__init__(option_strings, dest, **kwargs)
        self.keys = keys

    def __call__(self, parser, namespace, values, option_string=None):
        if values == "":
            for key in self.keys:
                namespace.__dict__.pop(PREFIX + key, None)
            return
        for key, value in zip(self.keys, values if len(self.keys) > 1 else (values,)):
            setattr(namespace, PREFIX + key, value)


def add_alias(parser, *option_strings: str, keys: str | tuple[str, ...], help: str | None = None, **kwargs) -> None:
    """A documented short flag (`rg map --width W`) for `--map.width`: same destination, its own type."""
    keys = (keys,) if isinstance(keys, str) else keys
    also = "= " + ", ".join(f"--{k}" for k in keys)
    if "choices" not in kwargs:   # argparse's own metavar would name the destination
        kwargs.setdefault("metavar", option_strings[0].lstrip("-").replace("-", "_").upper())
    parser.add_argument(*option_strings, action=_Alias, keys=keys, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                        help=f"{help} ({also})" if help else also, **kwargs)


def was_given(args: argparse.Namespace, key: str) -> bool:
    """Whether the command line set the config field `key` ("reason.backend")."""
    return PREFIX + key in vars(args)


def _convert(value: Any, tp: Any) -> Any:
    """A command-line string as the field's type where it reads as one; otherwise as it is, for the
    schema to refuse with the key's name."""
    tp = _bare(tp)
    if isinstance(value, list):
        args = typing.get_args(tp) or (str,)
        return [_convert(v, args[min(i, len(args) - 1)] if Ellipsis not in args else args[0])
                for i, v in enumerate(value)]
    if isinstance(value, str) and tp in (int, float):
        try:
            return tp(value)
        except ValueError:
            return value
    return value


def given(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """The config fields the command line set: {section: {field: value}}."""
    out: dict[str, dict[str, Any]] = {}
    for dest, value in vars(args).items():
        if dest.startswith(PREFIX):
            name, _, key = dest[len(PREFIX):].partition(".")
            out.setdefault(name, {})[key] = _convert(value, _hints(sections()[name])[key])
    return out


def apply_overrides(cfg: RGConfig, args: argparse.Namespace) -> RGConfig:
    """cfg (the defaults or --config FILE) with the command line's fields over it, validated by the
    schema; an invalid value is a ConfigError naming its option (`--map.width: ...`)."""
    over = given(args)
    if not over:
        return cfg
    errors = []
    for name, fields in over.items():
        for key, value in fields.items():
            try:
                config_from_dict({name: {key: value}})
            except ConfigError as exc:
                errors.append(f"--{exc}")
    if errors:
        raise ConfigError("; ".join(errors))
    data = config_to_dict(cfg)
    for name, fields in over.items():
        data[name].update(fields)
    return config_from_dict(data)
