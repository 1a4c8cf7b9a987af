# Helpers of the workflow. Everything above the "workflow glue" line is plain Python that needs
# none of Snakemake's globals: tests load it alone (tests/test_workflow.py, test_settings.py).
import json
import math
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import jsonschema
import pandas as pd
import yaml
from snakemake.utils import validate

SOURCES = ("simulated", "raw", "images", "llff", "colmap", "nerfstudio")
# as seathru.io.dataset_readers.ARCHIVE_SUFFIXES (the workflow does not import the package)
ARCHIVE_SUFFIXES = (".zip", ".tar", ".tgz", ".gz", ".bz2", ".xz", ".7z", ".rar")
STEPS = ("simulate", "ingest", "poses", "export", "train", "render", "evaluate", "report")
# Flags the workflow sets itself in each step's shell line; neither a dataset's options nor
# the config may set them. Thread counts (`threads`, `workers`) come from `resources`.
RESERVED_FLAGS = {
    "simulate": {"out"},
    "ingest": {"input", "out", "subdir", "layout", "workers"},
    "poses": {"ingest", "out", "threads", "source", "source_dir"},
    "export": {"poses", "out"},
    "train": {"cameras", "out", "checkpoint_dir", "threads"},
    "render": {"model", "cameras", "out", "threads"},
    "evaluate": {"renders", "cameras", "train_dir", "truth", "out", "threads"},
    "report": {"results", "datasets", "logs", "out", "variants"},
}
# A sweep runs a dataset under named variants of its options (config `sweep`, sheet column
# `sweep`): `<dataset>+<variant>` is a dataset of its own from train on, on the dataset's
# simulate / ingest / poses outputs, so a variant may only change the steps after those.
SWEEP_STEPS = ("train", "render", "evaluate")
VARIANT_MARK = "+"
ALL_VARIANTS = "all"
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.-]*"


class SheetError(ValueError):
    """A malformed dataset sheet or configuration, found before any job starts."""


class OptionValueLoader(yaml.SafeLoader):
    """YAML for one value of the sheet's options column, with YAML 1.2 scalars: only true/false
    are booleans (`train.medium.mode=off` stays the string 'off') and 1e-3 is a number."""


OptionValueLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
OptionValueLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
OptionValueLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"))


def parse_options(text, where, reserved=RESERVED_FLAGS, steps=STEPS):
    """The options column, 'step.key=value; step.section.key=value', as nested dicts.

    >>> parse_options("train.medium.mode=off; train.seed=1", "row 2")
    {'train': {'medium': {'mode': 'off'}, 'seed': 1}}
    """
    options = {}
    for item in filter(None, (part.strip() for part in text.split(";"))):
        key, sep, value = item.partition("=")
        parts = [part.strip() for part in key.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise SheetError(f"{where}: option {item!r} is not of the form step.key=value "
                             "(or step.section.key=value)")
        step, names = parts[0], parts[1:]
        check_reserved(where, step, names[0], reserved, steps)
        node = options.setdefault(step, {})
        for depth, name in enumerate(names[:-1], start=1):
            node = node.setdefault(name, {})
            if not isinstance(node, dict):
                raise SheetError(f"{where}: {'.'.join(parts[:depth + 1])} is given a value and "
                                 "also used as a section")
        if names[-1] in node:
            raise SheetError(f"{where}: {key.strip()} is given twice (or is also a section)")
        try:
            node[names[-1]] = yaml.load(value.strip(), Loader=OptionValueLoader)
        except yaml.YAMLError as exc:
            raise SheetError(f"{where}: {key.strip()}: {value.strip()!r} is not a valid value "
                             f"({' '.join(str(exc).split())})") from None
    return options


def check_reserved(where, step, name, reserved=RESERVED_FLAGS, steps=STEPS):
    if step not in steps:
        raise SheetError(f"{where}: unknown step {step!r}; steps are {', '.join(steps)}")
    if name in reserved.get(step, ()):
        raise SheetError(f"{where}: {step}.{name} is set by the workflow and cannot be overridden")


def deep_merge(base, overrides):
    """``base`` updated by ``overrides``, recursing into nested sections (neither is changed)."""
    merged = dict(base or {})
    for key, value in (overrides or {}).items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def flatten_options(options, prefix=""):
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (as seathru.settings.flatten)."""
    flat = {}
    for key, value in options.items():
        if isinstance(value, dict):
            flat.update(flatten_options(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


# YAML 1.1 (Snakemake's config loader) reads off/on/no/yes as booleans: a boolean given for a
# setting that is not boolean stands for the word (`mode: off`), as in seathru.settings; and
# digits joined by colons as a base-60 number (`jpeg_chroma: 4:2:0` arrives as 14520).
YAML11_WORDS = {False: ("off", "no", "false"), True: ("on", "yes", "true")}
SEXAGESIMAL = re.compile(r"[1-9][0-9]*(?::[0-5]?[0-9])+")


def schema_node(schema, dotted):
    """The schema of the dotted setting ``a.b`` inside a section's schema, or None."""
    node = schema
    for part in dotted.split("."):
        node = (node or {}).get("properties", {}).get(part)
        if node is None:
            return None
    return node


def yaml11_word(value, node):
    """``value`` (a boolean) as the word it was, when ``node`` (its schema) is not boolean."""
    if node is None:
        return value
    types = node.get("type", [])
    if "boolean" in (types if isinstance(types, list) else [types]):
        return value
    if "enum" in node:
        choices = [choice for choice in node["enum"] if isinstance(choice, str)]
        if choices:
            return next((word for word in YAML11_WORDS[value] if word in choices), value)
    return YAML11_WORDS[value][0]


def yaml11_number(value, node):
    """``value`` (an integer) as the choice of ``node`` (its schema) YAML 1.1 read as it."""
    for choice in (node or {}).get("enum", []):
        if isinstance(choice, str) and SEXAGESIMAL.fullmatch(choice):
            number = 0
            for part in choice.split(":"):
                number = 60 * number + int(part)
            if number == value:
                return choice
    return value


def flag_list(options, schema=None):
    """Nested options as CLI arguments: ``--section.key-name VALUE``, booleans ``--x``/``--no-x``,
    lists as several values, None left out. With the section's ``schema``, a boolean given for a
    setting that is not boolean is its YAML 1.1 word (``mode: off`` -> ``--mode off``), an
    integer given for a choice of colon-joined digits that choice (``4:2:0``, read as 14520).

    The same output as ``seathru.settings.cli_flags(options, Settings)`` (tests/test_settings.py
    compares them); a copy, because the Snakemake process need not be able to import the package
    (with ``--software-deployment-method conda`` only the jobs' environment has it).
    """
    args = []
    for key, value in sorted(flatten_options(options).items()):
        name = key.replace("_", "-")
        if value is None:
            continue
        if isinstance(value, bool) and schema is not None:
            value = yaml11_word(value, schema_node(schema, key))
        elif isinstance(value, int) and schema is not None:
            value = yaml11_number(value, schema_node(schema, key))
        if isinstance(value, bool):
            args.append(f"--{name}" if value else f"--no-{name}")
        elif isinstance(value, (list, tuple)):
            args += [f"--{name}", *map(str, value)]
        else:
            args += [f"--{name}", str(value)]
    return args


def cli_flags(options, schema=None):
    """The options as one shell-quoted string of flags for a rule's shell line."""
    return " ".join(shlex.quote(arg) for arg in flag_list(options, schema))


def _known_names(schema):
    return ", ".join(schema.get("properties", {})) or "none"


def schema_error_message(error, prefix=()):
    """One line for a jsonschema error: the dotted field and what is wrong with it."""
    path = [*prefix, *map(str, error.absolute_path)]
    field = ".".join(path)
    schema, instance = error.schema, error.instance
    if error.validator == "additionalProperties" and isinstance(instance, dict):
        unknown = sorted(set(instance) - set(schema.get("properties", {})))
        name = ".".join([*path, unknown[0]])
        if not path:
            return f"{name} is not a configuration key; keys are {_known_names(schema)}"
        where = f" of 'seathru {path[0]}'" if path[0] in STEPS else ""
        return (f"{name} is not a setting{where}; known here: {_known_names(schema)} "
                "(every setting: config/README.md)")
    if error.validator == "type" and "properties" in schema and not isinstance(instance, dict):
        return (f"{field} is a section, not a value: set its fields ({field}.<name>, one of "
                f"{_known_names(schema)})")
    if error.validator == "type" and isinstance(instance, dict) and path:
        return f"{field} is a setting, not a section: give it a value ({field}=...)"
    if error.validator == "anyOf" and "description" in schema:
        return f"{field}: {instance!r} is not {schema['description']}"
    message = f"{field}: {error.message}" if field else error.message
    if error.validator == "type" and "array" in _types(schema) and isinstance(instance, str):
        items = [item for item in re.split(r"[\s,]+", instance.strip()) if item]
        message += f" (a list is written in brackets: {field}=[{', '.join(items)}])"
    if isinstance(instance, bool) and "enum" in schema:
        message += " (YAML reads off/no/on/yes as booleans: quote the word, e.g. 'off')"
    return message


def _types(node):
    types = node.get("type", [])
    return set(types if isinstance(types, list) else [types])


def read_text_values(data, schema):
    """``data`` with text standing for a number, boolean or list where the schema wants one read
    as a sheet value is: Snakemake reads nested ``--config`` values as text
    (``--config "train={max_minutes: 5}"`` gives '5')."""
    if isinstance(data, dict):
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        return {key: read_text_values(value, properties.get(key, extra if isinstance(extra, dict)
                                                              else {}))
                for key, value in data.items()}
    if isinstance(data, list) and isinstance(schema.get("items"), dict):
        return [read_text_values(item, schema["items"]) for item in data]
    # a value that may be one of several kinds (``anyOf``: a number or a word) is read as any
    alternatives = schema.get("anyOf", [schema])
    types = set().union(*(_types(alternative) for alternative in alternatives))
    words = [word for alternative in alternatives for word in alternative.get("enum", [])] + \
        [alternative["const"] for alternative in alternatives if "const" in alternative]
    wants_text = "string" in types or (not types and any(isinstance(w, str) for w in words))
    if isinstance(data, str) and not wants_text and (types or words):
        try:
            return yaml.load(data, Loader=OptionValueLoader)
        except yaml.YAMLError:
            return data
    return data


def schema_errors(schema, instance, prefix=()):
    """Every error of ``instance`` against ``schema`` as messages, in path order."""
    validator = jsonschema.validators.validator_for(schema)(schema)
    errors = sorted(validator.iter_errors(instance), key=lambda e: [str(p) for p in e.absolute_path])
    return [schema_error_message(error, prefix) for error in errors]


def check_config(config, schema):
    """Refuse a configuration with a reserved, unknown or ill-typed key (naming the field)."""
    for step in STEPS:
        for name in config.get(step) or {}:
            check_reserved(f"configuration section '{step}'", step, name)
    errors = schema_errors(schema, config)
    if errors:
        listing = "\n  ".join(errors)
        raise SheetError(f"configuration (config/config.yaml and --config): {listing}")


def check_dataset_options(config, options, where, schema):
    """Each step's config section updated by a row's options must satisfy the config schema."""
    errors = []
    for step, overrides in options.items():
        merged = deep_merge(config.get(step) or {}, overrides)
        errors += schema_errors(schema["properties"][step], merged, prefix=(step,))
    if errors:
        listing = f"\n  {where}: ".join(errors)
        raise SheetError(f"{where}: {listing}")


def variant_id(dataset, variant):
    """The id of a dataset run under a sweep variant: ``variant_id("demo", "fast")`` is
    ``demo+fast`` (results/demo+fast/, logs/demo+fast/)."""
    return f"{dataset}{VARIANT_MARK}{variant}"


def base_dataset(dataset_id):
    """The sheet's dataset an id runs on: ``demo+fast`` -> ``demo``, ``demo`` -> ``demo``."""
    return dataset_id.split(VARIANT_MARK, 1)[0]


def parse_sweep(sweep, config, schema, where="config/config.yaml"):
    """The configuration's ``sweep`` (variant name -> options text in the sheet's syntax) as
    variant name -> nested options, each checked like a sheet row's options (naming the variant).

    >>> parse_sweep({"fast": "train.preset=fast"}, {}, {"properties": {"train": {}}})
    {'fast': {'train': {'preset': 'fast'}}}
    """
    variants = {}
    for name, text in (sweep or {}).items():
        label = f"{where}: sweep variant {name!r}"
        if not re.fullmatch(NAME_PATTERN, str(name)) or name == ALL_VARIANTS:
            raise SheetError(f"{label}: a variant's name uses letters, digits, '_', '.', '-' and "
                             f"is not {ALL_VARIANTS!r}")
        if text is not None and not isinstance(text, str):
            raise SheetError(f"{label}: give its options as text, 'step.key=value; ...' (the "
                             "syntax of the sheet's options column)")
        options = parse_options(text or "", label)
        fixed = [step for step in options if step not in SWEEP_STEPS]
        if fixed:
            raise SheetError(
                f"{label}: {fixed[0]} options cannot vary in a sweep (a variant reuses its "
                f"dataset's simulate, ingest and poses outputs; only {', '.join(SWEEP_STEPS)} "
                "options may): make another row of the sheet instead")
        check_dataset_options(config, options, label, schema)
        variants[str(name)] = options
    return variants


def sweep_variants(cell, variants, where):
    """The variant names a sheet row's ``sweep`` cell asks for, in order without repeats:
    comma-separated names, ``all`` (every variant of the configuration) or empty (none)."""
    names = list(dict.fromkeys(n.strip() for n in str(cell or "").split(",") if n.strip()))
    if ALL_VARIANTS in names:
        return list(variants)
    unknown = [name for name in names if name not in variants]
    if unknown:
        known = ", ".join(variants) or "none (config/config.yaml has no 'sweep')"
        raise SheetError(f"{where}: field 'sweep': {unknown[0]!r} is not a sweep variant; "
                         f"variants (config/config.yaml 'sweep'): {known}, or {ALL_VARIANTS!r}")
    return names


def sweep_runs(dataset, cell, options, variants, config, schema, where):
    """The runs a sheet row's ``sweep`` cell adds: ``<dataset>+<variant>`` -> the row's options
    updated by the variant's (nested sections key by key), checked against the schema."""
    runs = {}
    for name in sweep_variants(cell, variants, where):
        merged = deep_merge(options, variants[name])
        check_dataset_options(config, merged, f"{where} with sweep variant {name!r}", schema)
        runs[variant_id(dataset, name)] = merged
    return runs


def ingest_for_protocol(ingest, evaluate):
    """The ingest options of a dataset whose evaluation runs NerfBaselines' protocol: its
    images at full resolution (``max_size: 0``) unless the options set a size, since the
    protocol compares renders with the stored images as they are.

    >>> ingest_for_protocol({}, {"protocol": "nerfbaselines"})
    {'max_size': 0}
    """
    if (evaluate or {}).get("protocol") == "nerfbaselines" and "max_size" not in (ingest or {}):
        return {**(ingest or {}), "max_size": 0}
    return ingest


# As seathru.nerf.device's BYTES_PER_TRAINING_PIXEL and TRAINING_MEMORY_BASE (the workflow does
# not import the package; tests/test_workflow.py checks they agree).
TRAIN_BYTES_PER_PIXEL = 55
TRAIN_MEMORY_BASE_MB = 1000


def training_memory_mb(cameras_json, attempt=1, fallback=16000):
    """``resources.train.mem_mb: auto``: the memory a train job asks for, from the pixels of
    the frames in its camera file (poses/cameras.json) as the train step estimates its peak,
    a fifth and 500 MB more (the interpreter, and the step's own check against what its job
    has left), doubled on each retry; ``fallback`` where the file cannot be read yet."""
    try:
        frames = json.loads(Path(cameras_json).read_text())["frames"]
        pixels = sum(int(frame["width"]) * int(frame["height"]) for frame in frames)
    except (OSError, ValueError, KeyError, TypeError):
        return fallback
    need_mb = TRAIN_MEMORY_BASE_MB + TRAIN_BYTES_PER_PIXEL * pixels / 1e6
    return int(math.ceil((1.2 * need_mb + 500) / 100) * 100) * 2 ** (max(1, attempt) - 1)


def sweep_flags(sweep):
    """The report's ``--variants NAME=OPTIONS ...`` (shell-quoted), or "" without a sweep."""
    pairs = [f"{name}={text or ''}" for name, text in (sweep or {}).items()]
    return " ".join(["--variants", *map(shlex.quote, pairs)]) if pairs else ""


# ================================================================================ workflow glue
# Generated from the steps' settings dataclasses ('python -m seathru.settings schema'); read
# as a file, so the Snakemake process needs no import of the package (conda deployment).
CONFIG_SCHEMA = yaml.safe_load(
    Path(workflow.source_path("../schemas/config.schema.yaml")).read_text())


def load_sheet(path, config):
    """The dataset sheet, indexed by dataset id, and each dataset's parsed options."""
    if not Path(path).is_file():
        raise SheetError(f"dataset sheet {path} not found (set 'datasets' in config/config.yaml)")
    sheet = pd.read_csv(path, sep="\t", dtype=str, keep_default_na=False, comment="#")
    missing = [c for c in ("dataset", "source", "path", "options") if c not in sheet.columns]
    if missing:
        raise SheetError(f"{path}: missing column {missing[0]!r}; the sheet needs the columns "
                         "dataset, source, path, options (tab-separated)")
    # ~ and environment variables ($SCRATCH/dives on a cluster) as a shell would read them
    sheet["path"] = [os.path.expandvars(os.path.expanduser(p)) if p else p
                     for p in sheet["path"]]
    options, runs = {}, {}
    for index, row in sheet.iterrows():
        where = f"{path} row {index + 2} (dataset {row['dataset']!r})"
        if row["source"] not in SOURCES:
            raise SheetError(f"{where}: field 'source': {row['source']!r} is not one of "
                             f"{', '.join(SOURCES)}")
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", row["dataset"]):
            raise SheetError(f"{where}: field 'dataset': use letters, digits, '_', '.', '-'")
        validate(pd.DataFrame([row]), schema="../schemas/datasets.schema.yaml")
        if row["source"] != "simulated" and not Path(row["path"]).exists():
            unset = re.findall(r"\$\{?(\w+)", row["path"])
            hint = (f" (the environment variable {unset[0]} is not set)" if unset else
                    f" (relative paths are read from the working folder {os.getcwd()})"
                    if not Path(row["path"]).is_absolute() else "")
            raise SheetError(f"{where}: field 'path': {row['path']!r} does not exist{hint}")
        if row["source"] != "simulated" and not Path(row["path"]).is_dir():
            archive = row["path"].lower().endswith(ARCHIVE_SUFFIXES)
            raise SheetError(f"{where}: field 'path': {row['path']!r} is "
                             + ("an archive: unpack it and give the folder that holds the images"
                                if archive else "a file: give the folder that holds the images"))
        options[row["dataset"]] = parse_options(row["options"], where)
        check_dataset_options(config, options[row["dataset"]], where, CONFIG_SCHEMA)
        if "sweep" in sheet.columns:
            runs.update(sweep_runs(row["dataset"], row["sweep"], options[row["dataset"]],
                                   VARIANTS, config, CONFIG_SCHEMA, where))
    duplicated = sheet["dataset"][sheet["dataset"].duplicated()].tolist()
    if duplicated:
        raise SheetError(f"{path}: dataset id {duplicated[0]!r} appears more than once")
    return sheet.set_index("dataset", drop=False), {**options, **runs}


config.update(read_text_values(config, CONFIG_SCHEMA))
check_config(config, CONFIG_SCHEMA)
RESULTS = config["results"]
LOGS = config["logs"]
VARIANTS = parse_sweep(config.get("sweep"), config, CONFIG_SCHEMA)
SHEET, OPTIONS = load_sheet(config["datasets"], config)
DATASETS = list(SHEET.index)            # the sheet's rows: every stage
RUNS = list(OPTIONS)                    # those and each <dataset>+<variant>: train and after

# envs/seathru.post-deploy.sh installs the package from this checkout into the conda
# environment Snakemake builds; it runs from a copy under .snakemake/conda/ in the working
# directory, so it cannot find the checkout by its own location. Snakemake runs it from this
# process, which hands it this variable (set here, so it is not an `envvars:` the user sets).
if (Path(workflow.basedir).parent / "pyproject.toml").is_file():
    os.environ.update(SEATHRU_SOURCE_DIR=str(Path(workflow.basedir).parent.resolve()))


def id_pattern(ids):
    """A wildcard constraint matching exactly these dataset ids."""
    return "|".join(map(re.escape, ids)) if ids else "NO_DATASET"


def step_options(dataset, step):
    """The step's configuration for one dataset: the config section updated by the sheet's
    options (nested sections merged key by key)."""
    merged = deep_merge(config.get(step) or {}, OPTIONS.get(dataset, {}).get(step, {}))
    if step == "ingest":
        return ingest_for_protocol(merged, step_options(dataset, "evaluate"))
    return merged


def flags(step):
    """A params function: the step's flags for the job's dataset (a change reruns the job)."""
    schema = CONFIG_SCHEMA["properties"][step]
    return lambda wildcards: cli_flags(step_options(wildcards.dataset, step), schema)


def resource(rule_name, key):
    table = config["resources"]
    return table.get(rule_name, {}).get(key, table["default"][key])


def rule_resources(rule_name):
    mem_mb = resource(rule_name, "mem_mb")
    if mem_mb == "auto":
        if rule_name != "train":
            raise SheetError(f"config/config.yaml: resources.{rule_name}.mem_mb: 'auto' is "
                             "known for train only; give this rule's memory in MB")
        # evaluated when the job is ready to run, its camera file written
        mem_mb = lambda wildcards, input, attempt: training_memory_mb(  # noqa: E731
            Path(input[0], "cameras.json"), attempt)
    return dict(mem_mb=mem_mb, runtime=resource(rule_name, "runtime"),
                gpu=resource(rule_name, "gpu"))


def source(dataset):
    return SHEET.loc[base_dataset(dataset), "source"]


def base_dir(wildcards, stage):
    """A stage of the dataset a run is on (simulate, ingest, poses: shared by its variants)."""
    return dataset_dir(base_dataset(wildcards.dataset), stage)


def poses_input(wildcards):
    return base_dir(wildcards, "poses")


def dataset_dir(dataset, stage):
    return f"{RESULTS}/{dataset}/{stage}"


def log_file(stage):
    return f"{LOGS}/{{dataset}}/{stage}.log"


def benchmark_file(stage):
    return f"{LOGS}/{{dataset}}/{stage}.benchmark.tsv"


def evaluated_datasets():
    """Datasets the report waits for: all of them, or in a partial report those that finished."""
    if not config.get("report_partial", False):
        return RUNS
    return [ds for ds in RUNS if Path(dataset_dir(ds, "evaluate"), "summary.json").exists()]


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
    """Where ingest finds a dataset's images: the simulation's raw/ (its camera JPEGs with
    ingest.images=jpeg), the sheet's folder (raw, images; ingest.images may name a subfolder),
    or the images a posed dataset holds in its own layout (llff, colmap, nerfstudio: --layout;
    ingest.images chooses the image folder)."""
    kind = source(wildcards.dataset)
    if kind == "simulated":
        jpeg = step_options(wildcards.dataset, "ingest").get("images") == "jpeg"
        return "--subdir jpeg" if jpeg else "--subdir raw --kind raw"
    if kind == "raw":
        return "--kind raw"
    if kind in ("llff", "colmap", "nerfstudio"):
        return f"--layout {kind}"
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
        "poses": base_dir(wildcards, "poses"),
        "train": rules.train.output.water.format(dataset=wildcards.dataset),
    }
    if source(wildcards.dataset) == "simulated":
        inputs["simulation"] = base_dir(wildcards, "simulate")
    return inputs


def truth_flag(wildcards):
    if source(wildcards.dataset) == "simulated":
        return f"--truth {shlex.quote(base_dir(wildcards, 'simulate'))}/truth"
    return ""
