import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pandas as pd
import yaml
from snakemake.utils import validate

validate(config, schema="../schemas/config.schema.yaml")

SOURCES = ("simulated", "raw", "images", "llff", "colmap", "nerfstudio")
STEPS = ("simulate", "ingest", "poses", "train", "render", "evaluate", "report")
RESULTS = config["results"]
LOGS = config["logs"]
# Flags the rules set themselves; a dataset's options may not override them.
RESERVED_FLAGS = {"input", "out", "threads", "cameras", "model", "renders", "train_dir", "truth",
                  "ingest", "source", "source_dir", "checkpoint_dir", "results", "datasets", "logs",
                  "subdir"}


class SheetError(ValueError):
    """A malformed dataset sheet or configuration, found before any job starts."""


def _step_flag_names():
    """Long option names of every step's CLI, or None when the package is not importable here."""
    try:
        from seathru.cli import build_parser
    except ImportError:
        return None
    parser = build_parser()
    names = {}
    for action in parser._subparsers._group_actions:
        for step, sub in action.choices.items():
            long_names = {opt[2:].replace("-", "_") for act in sub._actions
                          for opt in act.option_strings if opt.startswith("--")}
            # --no-x negates a boolean --x, which the config writes as x: false
            names[step] = long_names | {n.removeprefix("no_") for n in long_names}
    return names


STEP_FLAGS = _step_flag_names()


def _check_step_keys(where, step, keys):
    if step not in STEPS:
        raise SheetError(f"{where}: unknown step {step!r}; steps are {', '.join(STEPS)}")
    bad = sorted(set(keys) & RESERVED_FLAGS)
    if bad:
        raise SheetError(f"{where}: {step}.{bad[0]} is set by the workflow and cannot be overridden")
    if STEP_FLAGS is not None and step in STEP_FLAGS:
        unknown = sorted(set(keys) - STEP_FLAGS[step])
        if unknown:
            raise SheetError(
                f"{where}: {step}.{unknown[0]} is not an option of 'seathru {step}' "
                f"(see 'seathru {step} --help')")


def _parse_options(text, where):
    options = {}
    for item in filter(None, (part.strip() for part in text.split(";"))):
        key, sep, value = item.partition("=")
        step, dot, name = key.strip().partition(".")
        if not sep or not dot or not name:
            raise SheetError(f"{where}: option {item!r} is not of the form step.key=value")
        _check_step_keys(where, step, [name])
        options.setdefault(step, {})[name] = yaml.safe_load(value.strip())
    return options


def load_sheet(path):
    if not Path(path).is_file():
        raise SheetError(f"dataset sheet {path} not found (set 'datasets' in config/config.yaml)")
    sheet = pd.read_csv(path, sep="\t", dtype=str, keep_default_na=False, comment="#")
    missing = [c for c in ("dataset", "source", "path", "options") if c not in sheet.columns]
    if missing:
        raise SheetError(f"{path}: missing column {missing[0]!r}; the sheet needs the columns "
                         "dataset, source, path, options (tab-separated)")
    for index, row in sheet.iterrows():
        where = f"{path} row {index + 2} (dataset {row['dataset']!r})"
        if row["source"] not in SOURCES:
            raise SheetError(f"{where}: field 'source': {row['source']!r} is not one of "
                             f"{', '.join(SOURCES)}")
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", row["dataset"]):
            raise SheetError(f"{where}: field 'dataset': use letters, digits, '_', '.', '-'")
        validate(pd.DataFrame([row]), schema="../schemas/datasets.schema.yaml")
        if row["source"] != "simulated" and not Path(row["path"]).exists():
            raise SheetError(f"{where}: field 'path': {row['path']!r} does not exist")
    duplicated = sheet["dataset"][sheet["dataset"].duplicated()].tolist()
    if duplicated:
        raise SheetError(f"{path}: dataset id {duplicated[0]!r} appears more than once")
    return sheet.set_index("dataset", drop=False)


for _step in STEPS:
    _check_step_keys(f"config section '{_step}'", _step, config.get(_step) or {})
SHEET = load_sheet(config["datasets"])
OPTIONS = {ds: _parse_options(SHEET.loc[ds, "options"], f"{config['datasets']} dataset {ds!r}")
           for ds in SHEET.index}
DATASETS = list(SHEET.index)


wildcard_constraints:
    dataset="|".join(map(re.escape, DATASETS)) if DATASETS else "NO_DATASET",


def step_options(dataset, step):
    """The step's configuration for one dataset: config defaults updated by the sheet's options."""
    merged = dict(config.get(step) or {})
    merged.update(OPTIONS.get(dataset, {}).get(step, {}))
    return merged


def cli_flags(options):
    """Render options as CLI flags: key_name -> --key-name VALUE, booleans as --key/--no-key."""
    parts = []
    for key, value in sorted(options.items()):
        name = key.replace("_", "-")
        if value is None:
            continue
        if isinstance(value, bool):
            parts.append(f"--{name}" if value else f"--no-{name}")
        elif isinstance(value, (list, tuple)):
            parts.append(f"--{name} " + " ".join(shlex.quote(str(v)) for v in value))
        else:
            parts.append(f"--{name} {shlex.quote(str(value))}")
    return " ".join(parts)


def flags(step):
    """A params function: the step's flags for the job's dataset (a change reruns the job)."""
    return lambda wildcards: cli_flags(step_options(wildcards.dataset, step))


def resource(rule_name, key):
    table = config["resources"]
    return table.get(rule_name, {}).get(key, table["default"][key])


def rule_resources(rule_name):
    return dict(mem_mb=resource(rule_name, "mem_mb"), runtime=resource(rule_name, "runtime"),
                gpu=resource(rule_name, "gpu"))


def source(dataset):
    return SHEET.loc[dataset, "source"]


def dataset_dir(dataset, stage):
    return f"{RESULTS}/{dataset}/{stage}"


def log_file(stage):
    return f"{LOGS}/{{dataset}}/{stage}.log"


def benchmark_file(stage):
    return f"{LOGS}/{{dataset}}/{stage}.benchmark.tsv"


def evaluated_datasets():
    """Datasets the report waits for: all of them, or in a partial report those that finished."""
    if not config.get("report_partial", False):
        return DATASETS
    return [ds for ds in DATASETS if Path(dataset_dir(ds, "evaluate"), "summary.json").exists()]


def build_partial_report(log):
    """After a failure: build the report over the datasets that finished, listing the others.

    With --keep-going the other datasets finish, but the report job waits for all of them and
    is skipped; a second, report-only run with report_partial=True makes it anyway.
    """
    if config.get("report_partial", False):
        return
    settings = Path(LOGS, ".partial_report_config.yaml")
    settings.parent.mkdir(parents=True, exist_ok=True)
    settings.write_text(yaml.safe_dump({**config, "report_partial": True}))
    command = [sys.executable, "-m", "snakemake", "--snakefile", workflow.main_snakefile,
               "--cores", "1", "--nolock", "--configfile", str(settings), "--keep-going",
               "report"]
    print("Some jobs failed; building the report over the datasets that finished:",
          " ".join(command), file=sys.stderr)
    subprocess.run(command, check=False)


REPORT_DIR = f"{RESULTS}/report"


def report_outputs():
    return [f"{REPORT_DIR}/summary.csv", f"{REPORT_DIR}/summary.html"]


def ingest_input(wildcards):
    if source(wildcards.dataset) == "simulated":
        return dataset_dir(wildcards.dataset, "simulate")
    return SHEET.loc[wildcards.dataset, "path"]


def ingest_source_flags(wildcards):
    kind = source(wildcards.dataset)
    if kind == "simulated":
        return "--subdir raw --kind raw"
    if kind == "raw":
        return "--kind raw"
    if kind == "colmap":
        return "--subdir images"
    return ""


def poses_source_flags(wildcards):
    kind = source(wildcards.dataset)
    path = SHEET.loc[wildcards.dataset, "path"]
    readers = {"llff": "llff", "colmap": "colmap-model", "nerfstudio": "nerfstudio"}
    if kind in readers:
        return f"--source {readers[kind]} --source-dir {shlex.quote(path)}"
    return "--source colmap"


def evaluate_inputs(wildcards):
    inputs = {
        "renders": dataset_dir(wildcards.dataset, "render"),
        "poses": dataset_dir(wildcards.dataset, "poses"),
        "train": rules.train.output.water.format(dataset=wildcards.dataset),
    }
    if source(wildcards.dataset) == "simulated":
        inputs["simulation"] = dataset_dir(wildcards.dataset, "simulate")
    return inputs


def truth_flag(wildcards):
    if source(wildcards.dataset) == "simulated":
        return f"--truth {RESULTS}/{wildcards.dataset}/simulate/truth"
    return ""
