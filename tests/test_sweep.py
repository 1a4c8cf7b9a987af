"""Sweeps: a dataset run under named variants of its options (config `sweep`, sheet column
`sweep`) as `<dataset>+<variant>`: the helpers of workflow/rules/common.smk, the jobs a dry run
plans, and the report's reading of the same sheet (seathru.io.sheet.expand_sweeps)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pandas as pd
import pytest
import yaml

from seathru.errors import PipelineError
from seathru.io.sheet import expand_sweeps, read_sheet, variant_options
from tests.conftest import REPO_ROOT, workflow_helpers
from tests.test_workflow import _shell_commands, snakemake

HELPERS = workflow_helpers()
SCHEMA = yaml.safe_load((REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml").read_text())
CONFIG = {"train": {"max_minutes": 3.0, "medium": {"mode": "auto"}}}
SWEEP = {"fast": "train.preset=fast", "long": "train.max_minutes=10; render.downscale=2",
         "paper": "train.preset=paper; train.medium.mode=view"}


def _variants(sweep=SWEEP, config=CONFIG):
    return HELPERS["parse_sweep"](sweep, config, SCHEMA)


def test_variants_parse_to_nested_options():
    variants = _variants()
    assert list(variants) == ["fast", "long", "paper"]
    assert variants["long"] == {"train": {"max_minutes": 10}, "render": {"downscale": 2}}
    assert variants["paper"] == {"train": {"preset": "paper", "medium": {"mode": "view"}}}
    assert HELPERS["parse_sweep"](None, CONFIG, SCHEMA) == {}


@pytest.mark.parametrize(("sweep", "expected"), [
    ({"quick": "train.medium.mode=soup"},
     r"sweep variant 'quick': train\.medium\.mode: 'soup' is not one of"),
    ({"quick": "train.no_such=1"},
     r"sweep variant 'quick': train\.no_such is not a setting of 'seathru train'"),
    ({"quick": "train.preset=turbo"}, r"sweep variant 'quick': train\.preset: 'turbo'"),
    ({"quick": "train.preset"}, r"sweep variant 'quick': option 'train.preset' is not of the form"),
    ({"small": "ingest.max_size=100"},
     r"sweep variant 'small': ingest options cannot vary in a sweep .*another row"),
    ({"moved": "train.out=/tmp"}, r"sweep variant 'moved': train\.out is set by the workflow"),
    ({"all": "train.seed=1"}, r"sweep variant 'all': .* is not 'all'"),
    ({"two words": "train.seed=1"}, r"sweep variant 'two words': a variant's name"),
    ({"quick": {"train": {"seed": 1}}}, r"sweep variant 'quick': give its options as text"),
])
def test_a_bad_variant_is_refused_naming_it(sweep, expected):
    with pytest.raises(HELPERS["SheetError"], match=expected):
        _variants(sweep)


def test_sweep_cells_name_variants_or_all():
    variants = _variants()
    names = HELPERS["sweep_variants"]
    assert names("", variants, "row 2") == []
    assert names(" fast , paper,fast ", variants, "row 2") == ["fast", "paper"]
    assert names("all", variants, "row 2") == ["fast", "long", "paper"]
    with pytest.raises(HELPERS["SheetError"],
                       match=r"row 2: field 'sweep': 'fats' is not a sweep variant; variants "
                             r"\(config/config.yaml 'sweep'\): fast, long, paper, or 'all'"):
        names("fast, fats", variants, "row 2")
    with pytest.raises(HELPERS["SheetError"], match="none .config/config.yaml has no 'sweep'"):
        names("fast", {}, "row 2")


def test_a_sweep_run_has_the_rows_options_updated_by_the_variants():
    row_options = HELPERS["parse_options"](
        "train.max_minutes=2; train.medium.mode=global; simulate.water=clear", "row 2")
    runs = HELPERS["sweep_runs"]("dive", "long, paper", row_options, _variants(), CONFIG,
                                 SCHEMA, "row 2")
    assert list(runs) == ["dive+long", "dive+paper"]
    assert runs["dive+long"]["train"] == {"max_minutes": 10, "medium": {"mode": "global"}}
    assert runs["dive+long"]["render"] == {"downscale": 2}
    assert runs["dive+paper"]["train"] == {"max_minutes": 2, "preset": "paper",
                                           "medium": {"mode": "view"}}
    assert runs["dive+paper"]["simulate"] == {"water": "clear"}   # the row's own, unchanged
    assert row_options["train"] == {"max_minutes": 2, "medium": {"mode": "global"}}
    assert HELPERS["base_dataset"]("dive+paper") == "dive" == HELPERS["base_dataset"]("dive")
    assert HELPERS["variant_id"]("dive", "fast") == "dive+fast"


def test_report_flags_carry_the_variants():
    flags = HELPERS["sweep_flags"]({"fast": "train.preset=fast; train.seed=2", "plain": None})
    assert shlex.split(flags) == ["--variants", "fast=train.preset=fast; train.seed=2", "plain="]
    assert HELPERS["sweep_flags"](None) == ""
    assert variant_options(shlex.split(flags)[1:]) == {"fast": "train.preset=fast; train.seed=2",
                                                       "plain": ""}
    with pytest.raises(PipelineError, match="NAME=OPTIONS"):
        variant_options(["fast"])


def test_the_report_expands_the_sheet_as_the_workflow_does(tmp_path):
    sheet = tmp_path / "sheet.tsv"
    sheet.write_text("dataset\tsource\tpath\toptions\tsweep\n"
                     "dive\tsimulated\t\ttrain.max_minutes=2\tlong, fast\n"
                     "other\tsimulated\t\t\t\n"
                     "every\tsimulated\t\t\tall\n")
    table = expand_sweeps(read_sheet(sheet), SWEEP, sheet)
    variants = _variants()
    expected = []
    for _, row in read_sheet(sheet).iterrows():
        expected.append(row["dataset"])
        expected += [HELPERS["variant_id"](row["dataset"], name) for name in
                     HELPERS["sweep_variants"](row["sweep"], variants, "row")]
    assert table["dataset"].tolist() == expected
    dive_long = table.set_index("dataset").loc["dive+long"]
    assert (dive_long["base"], dive_long["variant"], dive_long["source"]) == ("dive", "long",
                                                                              "simulated")
    assert dive_long["options"] == "train.max_minutes=2; train.max_minutes=10; render.downscale=2"
    assert table.set_index("dataset").loc["other", "variant"] == ""
    no_column = tmp_path / "plain.tsv"
    no_column.write_text("dataset\tsource\tpath\toptions\nd\tsimulated\t\t\n")
    assert expand_sweeps(read_sheet(no_column), SWEEP)["dataset"].tolist() == ["d"]
    with pytest.raises(PipelineError, match=r"dataset 'dive': sweep variant 'long' is not given"):
        expand_sweeps(read_sheet(sheet), {"fast": ""}, sheet)


# ------------------------------------------------------------------------------- dry runs

def _sheet(tmp_path: Path, rows: list[str]) -> str:
    sheet = tmp_path / "sheet.tsv"
    sheet.write_text("\n".join(["dataset\tsource\tpath\toptions\tsweep", *rows]) + "\n")
    return str(sheet)


def test_a_sweep_run_trains_on_its_datasets_poses_and_writes_its_own_folders(tmp_path):
    sheet = _sheet(tmp_path, ["dive\tsimulated\t\ttrain.max_minutes=2\tfast, paper",
                              "plain\tsimulated\t\t\t"])
    result = snakemake("-n", "-p", "--cores", "1", "--forceall", "--config", f"datasets={sheet}")
    assert result.returncode == 0, result.stderr[-3000:]
    counts = dict(re.findall(r"^(\w+)\s+(\d+)$", result.stdout, re.M))
    assert {rule: counts[rule] for rule in ("simulate", "ingest", "poses", "export", "train",
                                            "render", "evaluate", "report")} == {
        "simulate": "2", "ingest": "2", "poses": "2", "export": "2", "train": "4",
        "render": "4", "evaluate": "4", "report": "1"}
    commands = _shell_commands(result.stdout)
    assert not any(dataset.startswith("dive+") for step, dataset in commands
                   if step in ("simulate", "ingest", "poses", "export"))

    def argv(step, dataset):
        return shlex.split(commands[(step, dataset)].split(" > ")[0])

    def value(args, flag):
        return args[args.index(flag) + 1]

    train = argv("train", "dive+fast")
    assert value(train, "--cameras") == "results/dive/poses/cameras.json"
    assert value(train, "--out") == "results/dive+fast/train"
    assert value(train, "--checkpoint-dir") == "results/dive+fast/checkpoints"
    assert value(train, "--preset") == "fast" and value(train, "--max-minutes") == "2"
    assert "--preset" not in argv("train", "dive") and "--preset" not in argv("train", "plain")
    assert value(argv("train", "dive+paper"), "--preset") == "paper"
    render = argv("render", "dive+paper")
    assert value(render, "--model") == "results/dive+paper/train/model.pt"
    assert value(render, "--cameras") == "results/dive/poses/cameras.json"
    evaluate = argv("evaluate", "dive+fast")
    assert value(evaluate, "--truth") == "results/dive/simulate/truth"
    assert value(evaluate, "--train-dir") == "results/dive+fast/train"
    assert value(evaluate, "--out") == "results/dive+fast/evaluate"
    report = next(c for (step, _), c in commands.items() if step == "report")
    assert "--variants" in shlex.split(report)
    assert "logs/dive+fast/train.log" in commands[("train", "dive+fast")]


def test_a_bad_variant_or_sweep_cell_is_refused_before_any_job(tmp_path):
    sheet = _sheet(tmp_path, ["dive\tsimulated\t\t\tfast"])
    result = snakemake("-n", "--cores", "1", "--config", f"datasets={sheet}",
                       "sweep={fast: 'train.medium.mode=soup'}")
    output = result.stdout + result.stderr
    assert result.returncode != 0 and "rule " not in result.stdout
    assert "config/config.yaml: sweep variant 'fast': train.medium.mode: 'soup'" in output, \
        output[-2000:]
    bad_cell = _sheet(tmp_path, ["dive\tsimulated\t\t\tfats"])
    result = snakemake("-n", "--cores", "1", "--config", f"datasets={bad_cell}")
    assert result.returncode != 0 and "rule " not in result.stdout
    assert (f"{bad_cell} row 2 (dataset 'dive'): field 'sweep': 'fats' is not a sweep variant"
            in result.stdout + result.stderr)


def test_the_default_configuration_names_the_presets_and_sweeps_nothing():
    config = yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text())
    assert set(config["sweep"]) >= {"fast", "quality", "paper"}
    _variants(config["sweep"], config)   # valid against the schema
    sheet = pd.read_csv(REPO_ROOT / "config" / "datasets.tsv", sep="\t", dtype=str,
                        keep_default_na=False, comment="#")
    assert "sweep" in sheet.columns and (sheet["sweep"] == "").all()
