"""One source of truth for settings: the steps' ``Settings`` dataclasses.

The committed config schema and the settings tables of config/README.md are what
``seathru.settings`` generates from them now; every step's CLI flags are those settings plus
the flags the workflow sets itself; the workflow's own copy of ``cli_flags`` renders options
exactly as ``seathru.settings.cli_flags``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import io
import re
import types
import typing

import pytest
import yaml
from hypothesis import given, settings as hypothesis_settings, strategies as st

from seathru import settings
from seathru.steps import STEP_ORDER
from tests.conftest import REPO_ROOT, workflow_helpers

SCHEMA_FILE = REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml"
CONFIG_README = REPO_ROOT / "config" / "README.md"
REGENERATE = "bash .ci/generate.sh"
MARKERS = re.compile(r"<!-- settings:begin[^\n]*-->\n(.*?)<!-- settings:end -->", re.S)

HELPERS = workflow_helpers()


def settings_class(step: str) -> type:
    """``seathru.steps.<step>.Settings``; fails the test naming the step when it has none."""
    module = importlib.import_module(f"seathru.steps.{step}")
    if not hasattr(module, "Settings"):
        pytest.fail(f"seathru.steps.{step} has no Settings dataclass yet")
    return module.Settings


@pytest.fixture(scope="module")
def step_classes() -> dict[str, type]:
    """Every step's Settings (settings.step_settings() needs them all)."""
    return {step: settings_class(step) for step in STEP_ORDER}


def _generated(command: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert settings.main([command]) == 0
    return out.getvalue()


def test_committed_schema_is_generated_from_the_dataclasses(step_classes):
    assert SCHEMA_FILE.read_text() == _generated("schema"), (
        f"{SCHEMA_FILE.relative_to(REPO_ROOT)} is stale: run {REGENERATE}")


def test_committed_schema_says_it_is_generated():
    first = SCHEMA_FILE.read_text().splitlines()[0]
    assert first.startswith("#") and "python -m seathru.settings schema" in first, first


def _readme_settings() -> str:
    match = MARKERS.search(CONFIG_README.read_text())
    assert match, f"{CONFIG_README}: the settings markers are missing"
    return match.group(1)


def test_config_readme_lists_the_current_settings(step_classes):
    assert _readme_settings().strip() == _generated("docs").strip(), (
        f"the settings tables of {CONFIG_README.relative_to(REPO_ROOT)} are stale: "
        f"run {REGENERATE}")


def test_settings_tables_are_well_formed_markdown(step_classes):
    """Every row of the generated tables has the header's four cells (a '|' inside a cell,
    e.g. 'grid | mlp', must be escaped or it splits the cell)."""
    bad = []
    for line in settings.settings_docs().splitlines():
        if line.startswith("|"):
            cells = re.split(r"(?<!\\)\|", line.strip())[1:-1]
            if len(cells) != 4:
                bad.append(line)
    assert not bad, f"{len(bad)} rows with a wrong number of cells, e.g. {bad[:3]}"


def _schema_keys(node: dict, prefix: str = "") -> list[str]:
    keys = []
    for name, child in node.get("properties", {}).items():
        if "properties" in child:
            keys += _schema_keys(child, f"{prefix}{name}.")
        else:
            keys.append(f"{prefix}{name}")
    return keys


def _step_help(step: str) -> str:
    """``seathru <step> --help``, through the public parser (argparse exits after help)."""
    from seathru.cli import build_parser

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        build_parser().parse_args([step, "--help"])
    return out.getvalue()


def _help_flags(help_text: str) -> set[str]:
    """Long option strings of the option lines of a help text ('  --x, --no-x  help')."""
    flags = set()
    for line in help_text.splitlines():
        if re.match(r"^  -", line):
            invocation = re.split(r"\s{2,}", line.strip())[0]
            flags |= set(re.findall(r"--[\w.-]+", invocation))
    return flags - {"--help"}


def _setting_flags(cls: type) -> set[str]:
    flags = set()
    for name in settings.field_names(cls):
        flag = "--" + name.replace("_", "-")
        flags.add(flag)
        if _field_type(cls, name) is bool:
            flags.add("--no-" + flag[2:])
    return flags


def _field_type(cls: type, dotted: str):
    head, _, rest = dotted.partition(".")
    tp = typing.get_type_hints(cls)[head]
    return _field_type(tp, rest) if rest else tp


@pytest.mark.parametrize("step", STEP_ORDER)
def test_cli_flags_schema_keys_and_dataclass_agree(step):
    cls = settings_class(step)
    fields = settings.field_names(cls)
    committed = yaml.safe_load(SCHEMA_FILE.read_text())["properties"][step]
    assert _schema_keys(committed) == fields, f"schema section {step!r} != {cls.__name__}"
    assert _schema_keys(settings.json_schema(cls)) == fields

    flags = _help_flags(_step_help(step))
    expected = _setting_flags(cls)
    assert expected <= flags, f"settings without a flag: {sorted(expected - flags)}"
    workflow_set = {"--" + name.replace("_", "-") for name in HELPERS["RESERVED_FLAGS"][step]}
    others = flags - expected - {"--verbose", "--version"}
    assert others <= workflow_set, (
        f"'seathru {step}' flags that are neither settings (so not settable from the config or "
        f"the sheet) nor set by the workflow (RESERVED_FLAGS in workflow/rules/common.smk): "
        f"{sorted(others - workflow_set)}")
    stale = {flag for flag in workflow_set - flags}
    assert not stale, f"RESERVED_FLAGS[{step!r}] names flags the step lacks: {sorted(stale)}"


# ----------------------------------------------------------- the workflow's copy of cli_flags

def _variants(cls: type) -> list[dict]:
    """Nested option dicts that exercise every kind of value of ``cls``'s settings."""
    defaults = settings.to_dict(cls())
    flat = settings.flatten(defaults)
    flipped, words, nulls, numbers = {}, {}, {}, {}
    for name, value in flat.items():
        tp = _field_type(cls, name)
        optional = typing.get_origin(tp) in (typing.Union, types.UnionType)
        inner = next(a for a in typing.get_args(tp) if a is not type(None)) if optional else tp
        if isinstance(value, bool):
            flipped[name] = not value
        elif typing.get_origin(inner) is typing.Literal or inner is str:
            words[name] = False   # `mode: off` as Snakemake's YAML 1.1 reads it
            for choice in typing.get_args(inner):   # `jpeg_chroma: 4:4:4` as it reads that
                number = yaml.safe_load(f"x: {choice}")["x"]
                if isinstance(number, int) and not isinstance(number, bool):
                    numbers[name] = number
        if value is None or optional:
            nulls[name] = None
    return [defaults, settings.nest(flipped), settings.nest(words), settings.nest(nulls),
            settings.nest(numbers), {}]


@pytest.mark.parametrize("step", STEP_ORDER)
def test_workflow_flags_equal_seathru_settings_cli_flags(step):
    cls = settings_class(step)
    schema = {**settings.json_schema(cls), "type": ["object", "null"]}
    for options in _variants(cls):
        assert HELPERS["flag_list"](options, schema) == settings.cli_flags(options, cls), options


_NAMES = st.from_regex(r"[a-z][a-z_]{0,5}", fullmatch=True)
_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 5) | st.floats(allow_nan=False, width=32)
    | st.text("ab _-.", max_size=4) | st.lists(st.integers(0, 9), max_size=3),
    lambda children: st.dictionaries(_NAMES, children, min_size=1, max_size=3), max_leaves=8)


@hypothesis_settings(max_examples=60, deadline=None)
@given(st.dictionaries(_NAMES, _VALUES, max_size=4))
def test_workflow_flags_equal_cli_flags_without_types(options):
    assert HELPERS["flag_list"](options) == settings.cli_flags(options)


def test_a_choice_yaml_11_reads_as_a_base_60_number_means_that_choice():
    from seathru.steps.simulate import Settings

    given = yaml.safe_load("jpeg_chroma: 4:4:4")        # as Snakemake reads the config
    assert given == {"jpeg_chroma": 14644}
    assert settings.from_mapping(Settings, given).jpeg_chroma == "4:4:4"
    assert settings.cli_flags(given, Settings) == ["--jpeg-chroma", "4:4:4"]
    with pytest.raises(settings.SettingsError, match="jpeg_chroma: 14645 is not one of"):
        settings.from_mapping(Settings, {"jpeg_chroma": 14645})


def test_sheet_values_are_yaml_with_only_true_and_false_as_booleans():
    parsed = HELPERS["parse_options"](
        "train.medium.mode=off; train.progress=false; train.loss.recon_eps=1e-3; "
        "train.field.density_res=[64, 96]; train.batch_rays=; simulate.water=clear",
        "row 2")
    assert parsed == {"train": {"medium": {"mode": "off"}, "progress": False,
                                "loss": {"recon_eps": 0.001}, "field": {"density_res": [64, 96]},
                                "batch_rays": None},
                      "simulate": {"water": "clear"}}


def test_sheet_options_merge_over_the_config_section_key_by_key():
    merged = HELPERS["deep_merge"]({"medium": {"mode": "global", "sigma_init": 0.1}, "seed": 1},
                                   {"medium": {"mode": "off"}})
    assert merged == {"medium": {"mode": "off", "sigma_init": 0.1}, "seed": 1}


def test_dataclass_defaults_are_valid_against_their_own_schema(step_classes):
    """Defaults written out in full pass the schema (a default outside its choices fails)."""
    import jsonschema

    for step, cls in step_classes.items():
        jsonschema.validate(settings.to_dict(cls()), settings.json_schema(cls))


def test_every_setting_has_help(step_classes):
    missing = []
    for step, cls in step_classes.items():
        def walk(klass, prefix):
            hints = typing.get_type_hints(klass)
            for f in dataclasses.fields(klass):
                if dataclasses.is_dataclass(hints[f.name]):
                    walk(hints[f.name], f"{prefix}{f.name}.")
                elif not f.metadata.get("help"):
                    missing.append(f"{prefix}{f.name}")
        walk(cls, f"{step}.")
    assert not missing, f"settings without help text: {missing}"
