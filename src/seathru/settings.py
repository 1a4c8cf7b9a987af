"""Typed settings: one dataclass per component, the single source of every step option.

A step's settings are a dataclass whose fields are declared with :func:`setting` (default and
help text); a field whose type is another settings dataclass is a nested section. From that one
declaration come

- the CLI flags: ``--name`` for top-level fields, ``--section.name`` for nested ones
  (underscores become hyphens; booleans get ``--x`` / ``--no-x``), with help and default;
- the parsed, type-checked value (:func:`from_namespace`, :func:`from_mapping`), refusing
  unknown keys with the dotted name of the key;
- the JSON schema of the step's section in ``config/config.yaml``
  (:func:`config_schema`, committed as ``workflow/schemas/config.schema.yaml``);
- the table of settings in ``config/README.md`` (:func:`markdown_table`).

Example::

    @dataclass
    class Budget:
        max_minutes: float = setting(3.0, help="wall-time budget in minutes")

    @dataclass
    class TrainSettings:
        budget: Budget = section(Budget)

    parser = argparse.ArgumentParser(); add_arguments(parser, TrainSettings)
    settings = from_namespace(TrainSettings, parser.parse_args(["--budget.max-minutes", "5"]))
    assert settings.budget.max_minutes == 5.0

``python -m seathru.settings schema`` prints the workflow's config schema and
``python -m seathru.settings docs`` the settings tables (tests check both files are current).
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys
import types
import typing
from pathlib import Path
from typing import Any, Literal, Mapping

from seathru.errors import PipelineError


class SettingsError(PipelineError):
    """A setting with an unknown name or a value of the wrong type or range."""


def setting(default: Any = dataclasses.MISSING, *, help: str,
            default_factory: Any = dataclasses.MISSING, length: int | None = None) -> Any:
    """A settings field: its default (or ``default_factory`` for lists) and its help text.

    Args:
        default: the value when nothing overrides it (``None`` = unset / automatic).
        help: one sentence for ``--help``, the schema and config/README.md.
        default_factory: for mutable defaults (lists).
        length: for list fields, the required number of items.
    """
    metadata = {"help": help, "length": length}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def section(cls: type) -> Any:
    """A nested settings section (its own dataclass), defaulting to that class's defaults."""
    return dataclasses.field(default_factory=cls, metadata={"help": (cls.__doc__ or "").strip()})


# ----------------------------------------------------------------------------------- types

def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _is_section(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


def _describe(tp: Any) -> str:
    tp, optional = _unwrap_optional(tp)
    origin = typing.get_origin(tp)
    if origin is Literal:
        text = " | ".join(str(a) for a in typing.get_args(tp))
    elif origin is list:
        text = f"list of {_describe(typing.get_args(tp)[0])}"
    else:
        text = getattr(tp, "__name__", str(tp))
    return f"{text} or null" if optional else text


def _coerce(tp: Any, value: Any, name: str, length: int | None = None) -> Any:
    """``value`` checked against ``tp`` (ints accepted for floats, strings for paths)."""
    inner, optional = _unwrap_optional(tp)
    if value is None:
        if optional:
            return None
        raise SettingsError(f"{name}: a value is required ({_describe(tp)})")
    origin = typing.get_origin(inner)
    if isinstance(value, bool) and inner is str:
        value = _yaml11_word(value, ())
    if origin is Literal:
        choices = typing.get_args(inner)
        value = _yaml11_choice(value, choices)
        if value not in choices:
            raise SettingsError(f"{name}: {value!r} is not one of "
                                f"{', '.join(map(str, choices))}")
        return value
    if origin is list:
        if not isinstance(value, (list, tuple)):
            raise SettingsError(f"{name}: expected a list, got {value!r}")
        if length is not None and len(value) != length:
            raise SettingsError(f"{name}: expected {length} values, got {len(value)}")
        item_type = typing.get_args(inner)[0]
        return [_coerce(item_type, v, f"{name}[{i}]") for i, v in enumerate(value)]
    if inner is bool:
        if not isinstance(value, bool):
            raise SettingsError(f"{name}: expected true or false, got {value!r}")
        return value
    if inner is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SettingsError(f"{name}: expected an integer, got {value!r}")
        return value
    if inner is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingsError(f"{name}: expected a number, got {value!r}")
        return float(value)
    if inner is str:
        if not isinstance(value, str):
            raise SettingsError(f"{name}: expected a string, got {value!r}")
        return value
    if inner is Path:
        if not isinstance(value, (str, Path)):
            raise SettingsError(f"{name}: expected a path, got {value!r}")
        return Path(value)
    raise TypeError(f"{name}: unsupported settings type {tp!r}")


# YAML 1.1 (PyYAML, Snakemake's config) reads off/on/no/yes as booleans: a string setting
# given as `mode: off` arrives as False and means the word. It also reads digits joined by
# colons as a base-60 number: `jpeg_chroma: 4:2:0` arrives as 14520 and means the choice.
_YAML11_WORDS = {False: ("off", "no", "false"), True: ("on", "yes", "true")}
_SEXAGESIMAL = re.compile(r"[1-9][0-9]*(?::[0-5]?[0-9])+")


def _yaml11_word(value: bool, choices: tuple) -> Any:
    words = _YAML11_WORDS[value]
    return next((w for w in words if w in choices), value) if choices else words[0]


def _sexagesimal(choice: Any) -> int | None:
    """The number YAML 1.1 reads ``choice`` as when it is digits joined by colons, else None."""
    if not isinstance(choice, str) or not _SEXAGESIMAL.fullmatch(choice):
        return None
    number = 0
    for part in choice.split(":"):
        number = 60 * number + int(part)
    return number


def _yaml11_choice(value: Any, choices: tuple) -> Any:
    """The choice a YAML 1.1 reading of it stands for (a boolean word, a base-60 number), else
    ``value`` itself."""
    if isinstance(value, bool):
        return _yaml11_word(value, choices)
    if isinstance(value, int):
        return next((c for c in choices if _sexagesimal(c) == value), value)
    return value


def _field_type(cls: type, dotted: str) -> Any:
    """The annotated type of a dotted setting name of ``cls``, or None when unknown."""
    head, _, rest = dotted.partition(".")
    tp = _hints(cls).get(head)
    if rest:
        return _field_type(tp, rest) if tp is not None and _is_section(tp) else None
    return tp


# --------------------------------------------------------------------------- construction

def from_mapping(cls: type, data: Mapping[str, Any] | None, where: str = "") -> Any:
    """An instance of ``cls`` from a nested mapping of overrides; unset fields keep defaults.

    Args:
        cls: a settings dataclass.
        data: nested ``{name: value or {section field: value}}``; ``None`` = all defaults.
        where: prefix of the dotted names in error messages (``"train"``).

    Returns:
        the settings, validated (a class's ``validate()`` runs last).

    Raises:
        SettingsError: naming the dotted key that is unknown or has a bad value.
    """
    data = dict(data or {})
    hints = _hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls)}
    prefix = f"{where}." if where else ""
    presets = getattr(cls, "PRESETS", None)
    if presets is not None and "preset" in known:
        # a named preset's values sit beneath the explicit ones
        name = data.get("preset", known["preset"].default)
        if isinstance(name, str) and name in presets:
            data = _deep_merge(presets[name], data)
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise SettingsError(f"{prefix}{unknown[0]} is not a setting; known: "
                            f"{', '.join(sorted(known))}")
    values = {}
    for name, value in data.items():
        tp = hints[name]
        if _is_section(tp):
            if not isinstance(value, Mapping):
                raise SettingsError(f"{prefix}{name} is a section; set its fields "
                                    f"({prefix}{name}.<field>)")
            values[name] = from_mapping(tp, value, f"{prefix}{name}")
        else:
            values[name] = _coerce(tp, value, f"{prefix}{name}", known[name].metadata.get("length"))
    instance = cls(**values)
    validate = getattr(instance, "validate", None)
    if callable(validate):
        try:
            validate()
        except ValueError as exc:
            raise SettingsError(f"{where or cls.__name__}: {exc}") from None
    return instance


def _deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = _deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def to_dict(settings: Any) -> dict:
    """Nested plain dict of a settings instance (JSON- and YAML-safe)."""
    out = {}
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = to_dict(value)
        elif isinstance(value, Path):
            out[f.name] = str(value)
        elif isinstance(value, tuple):
            out[f.name] = list(value)
        else:
            out[f.name] = value
    return out


def flatten(data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    out = {}
    for key, value in data.items():
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    """``{"a.b": 1}`` -> ``{"a": {"b": 1}}``."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        parts = key.split(".")
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def field_names(cls: type, prefix: str = "") -> list[str]:
    """Every dotted setting name of ``cls``, in declaration order."""
    names = []
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        if _is_section(hints[f.name]):
            names += field_names(hints[f.name], f"{prefix}{f.name}.")
        else:
            names.append(f"{prefix}{f.name}")
    return names


# ---------------------------------------------------------------------------------- CLI

def _default_of(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def add_arguments(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    """Add one flag per setting of ``cls`` (recursing into sections) to ``parser``.

    Flags are ``--name`` or ``--section.name`` with hyphens for underscores; parsed values land
    in the namespace under the dotted name, absent flags are left out (defaults come from the
    dataclass in :func:`from_namespace`).
    """
    hints = _hints(cls)
    group = parser if not prefix else parser.add_argument_group(
        f"{prefix.rstrip('.')} settings", (cls.__doc__ or "").strip().splitlines()[0]
        if cls.__doc__ else None)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if _is_section(tp):
            add_arguments(parser, tp, f"{prefix}{f.name}.")
            continue
        flag = "--" + (prefix + f.name).replace("_", "-")
        dest = prefix + f.name
        default = _default_of(f)
        help_text = f.metadata.get("help", "")
        help_text += f" (default: {default})" if default is not None else " (default: automatic)"
        inner, optional = _unwrap_optional(tp)
        origin = typing.get_origin(inner)
        kwargs: dict[str, Any] = {"dest": dest, "default": argparse.SUPPRESS,
                                  "help": help_text.replace("%", "%%")}  # argparse formats help
        if inner is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif origin is Literal:
            choices = typing.get_args(inner)
            kwargs["choices"] = choices
            kwargs["type"] = type(choices[0])
        elif origin is list:
            item = typing.get_args(inner)[0]
            kwargs["type"] = item if item in (int, float, str) else str
            kwargs["nargs"] = f.metadata.get("length") or "*"
            kwargs["metavar"] = item.__name__.upper()
        else:
            kwargs["type"] = inner if inner in (int, float, str, Path) else str
            kwargs["metavar"] = {int: "N", float: "X", Path: "PATH"}.get(inner, "TEXT")
        group.add_argument(flag, **kwargs)


def from_namespace(cls: type, namespace: argparse.Namespace) -> Any:
    """The settings of ``cls`` from parsed flags (added by :func:`add_arguments`)."""
    names = set(field_names(cls))
    given = {k: v for k, v in vars(namespace).items() if k in names}
    # errors name the step (``seathru.cli`` stores it) and the dotted setting
    return from_mapping(cls, nest(given), getattr(namespace, "step", "") or "")


def cli_flags(overrides: Mapping[str, Any], cls: type | None = None) -> list[str]:
    """Command-line arguments for nested overrides: the inverse of parsing them.

    With ``cls``, a boolean given for a string setting is read as the YAML 1.1 word it was
    (``mode: off``).

    >>> cli_flags({"medium": {"mode": "off"}, "seed": 1, "wb": None})
    ['--medium.mode', 'off', '--seed', '1']
    """
    args: list[str] = []
    for key, value in sorted(flatten(overrides).items()):
        name = key.replace("_", "-")
        if value is None:
            continue
        tp = _field_type(cls, key) if cls is not None else None
        inner = _unwrap_optional(tp)[0] if tp is not None else None
        choices = typing.get_args(inner) if typing.get_origin(inner) is Literal else ()
        if isinstance(value, bool) and tp is not None and inner is not bool:
            value = _yaml11_word(value, choices)
        elif choices:
            value = _yaml11_choice(value, choices)
        if isinstance(value, bool):
            args.append(f"--{name}" if value else f"--no-{name}")
        elif isinstance(value, (list, tuple)):
            args += [f"--{name}", *map(str, value)]
        else:
            args += [f"--{name}", str(value)]
    return args


# ------------------------------------------------------------------------ schema and docs

def _schema_of(tp: Any, f: dataclasses.Field | None) -> dict:
    inner, optional = _unwrap_optional(tp)
    origin = typing.get_origin(inner)
    if origin is Literal:
        choices = list(typing.get_args(inner))
        # YAML 1.1 readings standing for a choice (see _yaml11_choice)
        choices += [flag for flag, words in _YAML11_WORDS.items()
                    if any(w in choices for w in words)]
        choices += [number for number in map(_sexagesimal, choices) if number is not None]
        node: dict[str, Any] = {"enum": choices}
    elif origin is list:
        item = _schema_of(typing.get_args(inner)[0], None)
        node = {"type": "array", "items": item}
        length = f.metadata.get("length") if f is not None else None
        if length:
            node["minItems"] = node["maxItems"] = length
    else:
        node = {"type": {bool: "boolean", int: "integer", float: "number", str: "string",
                         Path: "string"}[inner]}
    if optional:
        if "enum" in node:
            node["enum"] = node["enum"] + [None]
        else:
            node["type"] = [node["type"], "null"]
    return node


def json_schema(cls: type) -> dict:
    """JSON schema (draft 2020-12) of a settings section: types, choices, defaults, help."""
    hints = _hints(cls)
    properties = {}
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if _is_section(tp):
            node = json_schema(tp)
        else:
            node = _schema_of(tp, f)
            default = _default_of(f)
            node["default"] = str(default) if isinstance(default, Path) else default
            node["description"] = f.metadata.get("help", "")
        properties[f.name] = node
    schema = {"type": "object", "additionalProperties": False, "properties": properties}
    if cls.__doc__:
        schema["description"] = " ".join(cls.__doc__.split())
    return schema


def markdown_table(cls: type, step: str) -> str:
    """A Markdown table of every setting of ``cls``: the key as written in config.yaml and the
    sheet (``step.section.name``), its type, default and meaning."""
    rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
    hints = _hints(cls)

    def walk(klass: type, prefix: str) -> None:
        hints_k = _hints(klass)
        for f in dataclasses.fields(klass):
            tp = hints_k[f.name]
            if _is_section(tp):
                walk(tp, f"{prefix}{f.name}.")
                continue
            default = _default_of(f)
            if isinstance(default, bool):
                default = str(default).lower()  # as YAML writes it
            shown = "automatic" if default is None else f"`{default}`"
            cells = [f"`{step}.{prefix}{f.name}`", _describe(tp), shown,
                     f.metadata.get("help", "")]
            rows.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")

    del hints
    walk(cls, "")
    return "\n".join(rows)


def step_settings() -> dict[str, type]:
    """Every pipeline step's settings class, in pipeline order."""
    import importlib

    from seathru.steps import STEP_ORDER

    return {name: importlib.import_module(f"seathru.steps.{name}").Settings
            for name in STEP_ORDER}


RESOURCE_SCHEMA = {
    "type": "object",
    "description": "per-rule resources (threads also set each step's thread count)",
    "additionalProperties": {
        "type": "object",
        "properties": {
            "threads": {"type": "integer", "minimum": 1},
            # auto (train only): the memory the dataset's photographs need (common.smk)
            "mem_mb": {"anyOf": [{"type": "integer", "minimum": 100}, {"const": "auto"}],
                       "description": "a memory in MB (at least 100) or auto (train only)"},
            "runtime": {"type": "integer", "minimum": 1},
            "gpu": {"type": "integer", "minimum": 0},
        },
        "additionalProperties": False,
    },
}


def config_schema() -> dict:
    """The schema of ``config/config.yaml``: workflow keys and one section per step."""
    steps = step_settings()
    properties: dict[str, Any] = {
        "datasets": {"type": "string", "description": "path of the dataset sheet (TSV)"},
        "results": {"type": "string", "description": "folder of the results"},
        "logs": {"type": "string", "description": "folder of the step logs"},
        "resources": RESOURCE_SCHEMA,
        "report_partial": {"type": "boolean", "default": False,
                           "description": "set by the workflow when it builds a report over "
                                          "the datasets that finished"},
        "sweep": {
            "type": ["object", "null"],
            "description": "named training variants: name -> options in the sheet's syntax "
                           "('train.preset=fast; train.max_minutes=1'; train, render and "
                           "evaluate only); a sheet row's 'sweep' column runs its dataset "
                           "under them as '<dataset>+<name>'",
            "propertyNames": {"pattern": "^[A-Za-z0-9][A-Za-z0-9_.-]*$"},
            "additionalProperties": {"type": ["string", "null"]},
        },
    }
    for name, cls in steps.items():
        properties[name] = {**json_schema(cls), "type": ["object", "null"]}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "description": "Pipeline configuration (config/config.yaml). Generated by "
                       "'python -m seathru.settings schema' from the step settings "
                       "dataclasses; do not edit by hand.",
        "type": "object",
        "properties": properties,
        "required": ["datasets", "results", "logs", "resources"],
        "additionalProperties": False,
    }


def settings_docs() -> str:
    """The Markdown settings reference: one table per step."""
    parts = []
    for name, cls in step_settings().items():
        doc = " ".join((cls.__doc__ or "").split())
        parts.append(f"### `{name}`\n\n{doc}\n\n{markdown_table(cls, name)}\n")
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    import json

    argv = sys.argv[1:] if argv is None else argv
    if argv == ["schema"]:
        import yaml

        print("# Generated by 'python -m seathru.settings schema'; do not edit by hand.")
        print(yaml.safe_dump(config_schema(), sort_keys=False, width=100), end="")
    elif argv == ["docs"]:
        print(settings_docs(), end="")
    elif argv == ["json"]:
        print(json.dumps(config_schema(), indent=1))
    else:
        print("usage: python -m seathru.settings schema|docs|json", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
