"""The Snakemake workflow: dry runs, lint, profiles, sheet and config validation against the
generated schema, the flags the rules pass, the conda environment and its post-deploy script,
the catalog conventions (.test/, LICENSE)."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO_ROOT, workflow_helpers

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python < 3.11
    tomllib = None


def snakemake(*args: str, cwd: Path = REPO_ROOT) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    return subprocess.run([sys.executable, "-m", "snakemake", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_dry_run_of_the_default_sheet_plans_every_stage():
    result = snakemake("-n", "--cores", "1", "--forceall")
    assert result.returncode == 0, result.stderr
    for rule in ("simulate", "ingest", "poses", "train", "render", "evaluate", "report"):
        assert re.search(rf"^{rule}\s+1$", result.stdout, re.M), f"{rule} not planned"


def test_lint_is_clean():
    result = snakemake("--lint")
    assert result.returncode == 0, result.stdout + result.stderr


def test_slurm_profile_dry_run():
    result = snakemake("-n", "--profile", "workflow/profiles/slurm", "--forceall")
    assert result.returncode == 0, result.stderr
    assert "train" in result.stdout


def _sheet(tmp_path: Path, rows: list[str], header: str = "dataset\tsource\tpath\toptions") -> str:
    sheet = tmp_path / "sheet.tsv"
    sheet.write_text("\n".join([header, *rows]) + "\n")
    return str(sheet)


@pytest.mark.parametrize(
    ("rows", "header", "expected"),
    [
        (["d1\tsimulated\t"], "dataset\tsource\tpath", "missing column 'options'"),
        (["d1\tsimulated\t\t", "d2\tsonar\t\t"], None, r"row 3 \(dataset 'd2'\): field 'source'"),
        (["d1\traw\t/no/such/dir\t"], None, r"row 2 \(dataset 'd1'\): field 'path'"),
        (["d1\tsimulated\t\tsimulate.views"], None, "not of the form step.key=value"),
        (["d1\tsimulated\t\tpainting.x=1"], None, "unknown step 'painting'"),
        (["d1\tsimulated\t\tingest.out=/tmp"], None, "set by the workflow"),
        (["d1\tsimulated\t\ttrain.threads=8"], None, "train.threads is set by the workflow"),
        (["d1\tsimulated\t\tingest.layout=llff"], None, "ingest.layout is set by the workflow"),
        (["d 1\tsimulated\t\t"], None, "field 'dataset'"),
        (["d1\tsimulated\t\t", "d1\tsimulated\t\t"], None, "appears more than once"),
        (["d1\tsimulated\t\t", "x\tsimulated\t\ttrain.medium.mode=soup"], None,
         r"row 3 \(dataset 'x'\): train\.medium\.mode: 'soup' is not one of"),
        (["d1\tsimulated\t\ttrain.medium=off"], None,
         r"row 2 \(dataset 'd1'\): train\.medium is a section, not a value"),
        (["d1\tsimulated\t\ttrain.medium.no_such=1"], None,
         r"train\.medium\.no_such is not a setting of 'seathru train'"),
        (["d1\tsimulated\t\ttrain.max_minutes=soon"], None,
         r"train\.max_minutes: 'soon' is not of type 'number'"),
        (["d1\tsimulated\t\tsimulate.sigma_attn=0.3 0.12 0.09"], None,
         r"simulate\.sigma_attn: '0\.3 0\.12 0\.09' is not of type 'array', 'null' \(a list is "
         r"written in brackets: simulate\.sigma_attn=\[0\.3, 0\.12, 0\.09\]\)"),
        (["d1\tsimulated\t\ttrain.seed=1; train.seed.x=2"], None,
         "train.seed is given a value and also used as a section"),
    ],
)
def test_malformed_sheet_is_refused_before_any_job(tmp_path, rows, header, expected):
    sheet = _sheet(tmp_path, rows, header or "dataset\tsource\tpath\toptions")
    result = snakemake("-n", "--cores", "1", "--config", f"datasets={sheet}")
    assert result.returncode != 0
    output = result.stdout + result.stderr
    assert re.search(expected, output), output[-2000:]
    assert "rule " not in result.stdout, "jobs were planned"


def _schema() -> dict:
    return yaml.safe_load((REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml").read_text())


@pytest.mark.parametrize("step", ["simulate", "ingest", "poses", "train", "render", "evaluate"])
def test_unknown_option_of_each_step_is_refused_naming_row_and_field(tmp_path, step):
    if step not in _schema()["properties"]:
        pytest.fail(f"the config schema has no section {step!r}: run bash .ci/generate.sh")
    sheet = _sheet(tmp_path, [f"d1\tsimulated\t\t{step}.no_such_flag=1"])
    result = snakemake("-n", "--cores", "1", "--config", f"datasets={sheet}")
    assert result.returncode != 0
    assert (f"{sheet} row 2 (dataset 'd1'): {step}.no_such_flag is not a setting of "
            f"'seathru {step}'") in result.stdout + result.stderr


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("resources={default: {threads: 0}}", r"resources\.default\.threads: 0 is less than"),
        ("train={medium: {mode: soup}}", r"train\.medium\.mode: 'soup' is not one of"),
        ("train={no_such: 1}", r"train\.no_such is not a setting of 'seathru train'"),
        ("trian={seed: 1}", r"trian is not a configuration key"),
        ("resources={train: {mem_mb: lots}}",
         r"resources\.train\.mem_mb: 'lots' is not a memory in MB \(at least 100\) or auto"),
        ("resources={render: {mem_mb: auto}}",
         r"resources\.render\.mem_mb: 'auto' is known for train only"),
    ],
)
def test_wrong_config_value_is_refused(override, expected):
    result = snakemake("-n", "--cores", "1", "--config", override)
    assert result.returncode != 0
    assert re.search(expected, result.stdout + result.stderr), (result.stdout + result.stderr)[-2000:]


def test_train_jobs_ask_for_the_memory_their_photographs_need(tmp_path):
    """``resources.train.mem_mb: auto``: a train job asks for what the train step's own check
    will want of its allocation (the interpreter's share aside), and not a blanket amount."""
    import json
    from types import SimpleNamespace

    from seathru.nerf import device

    helpers = workflow_helpers()
    memory_mb = helpers["training_memory_mb"]
    assert helpers["TRAIN_BYTES_PER_PIXEL"] == device.BYTES_PER_TRAINING_PIXEL
    assert helpers["TRAIN_MEMORY_BASE_MB"] * 1_000_000 == device.TRAINING_MEMORY_BASE
    cameras = tmp_path / "cameras.json"
    for count, width, height in ((24, 319, 239), (120, 1600, 1200)):
        cameras.write_text(json.dumps({"frames": [{"width": width, "height": height}] * count}))
        asked = memory_mb(cameras) * 1e6
        frames = [SimpleNamespace(width=width, height=height)] * count
        need = device.check_training_memory(frames, "cameras.json", available=asked - 4e8)
        assert asked <= 1.25 * need + 6e8
        assert memory_mb(cameras, attempt=2) == 2 * memory_mb(cameras)
    assert memory_mb(tmp_path / "not_yet.json", fallback=16000) == 16000
    assert yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text())[
        "resources"]["train"]["mem_mb"] == "auto"


def test_nested_config_values_given_as_text_are_read_as_values():
    # Snakemake reads nested --config values as text: '5', 'false', ['64', '96']
    result = snakemake("-n", "-p", "--cores", "1", "--forceall", "--config",
                       "train={max_minutes: 5, progress: false, field: {density_res: [64, 96]}, "
                       "medium: {mode: off}}")
    assert result.returncode == 0, result.stderr[-2000:]
    train = next(line for line in result.stdout.splitlines() if "seathru train" in line)
    for flags in ("--max-minutes 5", "--no-progress", "--field.density-res 64 96",
                  "--medium.mode off"):
        assert flags in train, train


def test_step_sections_may_be_left_out_of_the_config(tmp_path):
    config = yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text())
    config = {key: value for key, value in config.items()
              if key in ("datasets", "results", "logs", "resources")}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    result = snakemake("-n", "--cores", "1", "--forceall", "--configfile",
                       str(tmp_path / "config.yaml"))
    assert result.returncode == 0, result.stderr[-2000:]


def _shell_commands(output: str) -> dict[tuple[str, str], str]:
    """(step, dataset) -> the shell command a dry run with -p prints for that job."""
    commands = {}
    for line in output.splitlines():
        match = re.match(r"^\s*(?:Shell command: )?(seathru (\w+) .*)$", line)
        if match:
            argv = shlex.split(match.group(1).split(" > ")[0])
            dataset = next((Path(argv[i + 1]).parent.name for i, arg in enumerate(argv)
                            if arg == "--out"), None)
            commands[(match.group(2), dataset)] = match.group(1)
    return commands


def test_rules_pass_nested_options_as_flags_that_parse_back(tmp_path):
    """Config section + sheet options -> the rule's flags -> `seathru <step>`'s parser gives
    back the same settings (nested sections, booleans, lists, YAML 1.1 words, exponents)."""
    from seathru import settings
    from seathru.cli import build_parser

    config = yaml.safe_load((REPO_ROOT / "config" / "config.yaml").read_text())
    # as Snakemake reads `mode: off` (YAML 1.1): False
    config["train"] = {**config.get("train", {}), "medium": {"mode": False}, "progress": False}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    options = ("simulate.water=clear; simulate.jpeg_chroma=4:4:4; train.medium.sigma_init=1e-3; "
               "train.field.view_dependent_colour=true; train.field.density_res=[64, 96, 128]; "
               "train.device=cuda:0; render.path_frames=3")
    sheet = _sheet(tmp_path, ["plain\tsimulated\t\t", f"tuned\tsimulated\t\t{options}"])
    result = snakemake("-n", "-p", "--cores", "1", "--forceall", "--configfile",
                       str(tmp_path / "config.yaml"), "--config", f"datasets={sheet}")
    assert result.returncode == 0, result.stderr[-3000:]
    commands = _shell_commands(result.stdout)
    train = commands[("train", "tuned")]
    assert "--medium.mode off" in train and "--no-progress" in train, train
    assert "--field.density-res 64 96 128" in train and "--medium.sigma-init 0.001" in train
    assert "--medium.mode off" in commands[("train", "plain")]
    assert "--jpeg-chroma 4:4:4" in commands[("simulate", "tuned")]   # not base-60 14644
    assert "--field" not in commands[("train", "plain")]

    helpers = workflow_helpers()
    sheet_options = helpers["parse_options"](options, "test")
    parser = build_parser()
    checked = 0
    for (step, dataset), command in sorted(commands.items()):
        module = __import__(f"seathru.steps.{step}", fromlist=["Settings"])
        if step == "report" or not hasattr(module, "Settings"):
            continue
        argv = shlex.split(command.split(" > ")[0])[1:]
        parsed = settings.flatten(settings.to_dict(
            settings.from_namespace(module.Settings, parser.parse_args(argv))))
        wanted = helpers["deep_merge"](config.get(step) or {},
                                       sheet_options.get(step, {}) if dataset == "tuned" else {})
        expected = settings.flatten(settings.to_dict(settings.from_mapping(module.Settings,
                                                                           wanted)))
        given = settings.flatten(wanted)
        # settings the rule sets from the dataset's source (ingest --kind raw) are not compared
        for key, value in expected.items():
            if key in given or f"--{key.replace('_', '-')} " not in command:
                assert parsed[key] == value, (step, dataset, key, command)
        checked += 1
    assert checked >= 2, f"no step with Settings was checked: {sorted(commands)}"


def test_conda_environment_has_the_same_pins_as_pyproject():
    if tomllib is None:
        pytest.skip("tomllib needs Python 3.11")
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
    pins = {re.split(r"[=<>]", dep)[0].lower(): dep.lower() for dep in project["dependencies"]}
    env = yaml.safe_load((REPO_ROOT / "envs" / "seathru.yaml").read_text())
    pip_section = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict))
    env_pins = {re.split(r"[=<>]", dep)[0].lower(): dep.lower() for dep in pip_section
                if not dep.startswith("-")}
    assert env_pins == pins


def test_readme_test_command_is_what_ci_runs():
    readme = (REPO_ROOT / "README.md").read_text()
    block = readme.split("```")[1].strip().splitlines()
    commands = [line for line in block if line and not line.startswith(("#", "bash"))]
    assert len(commands) == 2
    assert commands[1] in (REPO_ROOT / ".ci" / "run").read_text()



def test_conda_environment_installs_the_package_after_creation_by_absolute_path():
    env = yaml.safe_load((REPO_ROOT / "envs" / "seathru.yaml").read_text())
    pip_section = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict))
    relative = [dep for dep in pip_section if dep.startswith("-") or "/" in dep or dep == "."]
    assert not relative, f"paths in the env file resolve against .snakemake/conda/: {relative}"
    script = REPO_ROOT / "envs" / "seathru.post-deploy.sh"
    assert script.read_text().startswith("#!"), "Snakemake picks the interpreter from the shebang"


def _fake_python(tmp_path: Path) -> tuple[dict, Path]:
    """An environment whose `python` only records its arguments (as `pip install` would get)."""
    bin_dir, log = tmp_path / "bin", tmp_path / "python-calls.log"
    bin_dir.mkdir()
    (bin_dir / "python").write_text(f'#!/bin/sh\necho "$PWD|$*" >> {shlex.quote(str(log))}\n')
    (bin_dir / "python").chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k != "SEATHRU_SOURCE_DIR"}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    return env, log


def _deploy_copy(workdir: Path) -> Path:
    """The post-deploy script where Snakemake puts it: <workdir>/.snakemake/conda/<hash>...."""
    target = workdir / ".snakemake" / "conda" / "0123abcd.post-deploy.sh"
    target.parent.mkdir(parents=True)
    shutil.copy(REPO_ROOT / "envs" / "seathru.post-deploy.sh", target)
    return target


def _run_deploy(script: Path, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    # as Snakemake runs it: the shebang's interpreter, the copy's path, the working directory
    interpreter = script.read_text().splitlines()[0][2:].split()
    return subprocess.run([*interpreter, str(script.relative_to(cwd)) if script.is_relative_to(cwd)
                           else str(script)], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=60)


def test_post_deploy_installs_the_checkout_the_workflow_names(tmp_path):
    workdir = tmp_path / "work"
    script = _deploy_copy(workdir)
    env, log = _fake_python(tmp_path)
    env["SEATHRU_SOURCE_DIR"] = str(REPO_ROOT)
    result = _run_deploy(script, workdir, env)
    assert result.returncode == 0, result.stderr
    assert log.read_text().splitlines() == [
        f"{workdir.resolve()}|-m pip install --no-deps --editable {REPO_ROOT.resolve()}"]


def test_post_deploy_finds_the_checkout_above_its_copy(tmp_path):
    checkout = tmp_path / "checkout"
    script = _deploy_copy(checkout)
    shutil.copy(REPO_ROOT / "pyproject.toml", checkout / "pyproject.toml")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env, log = _fake_python(tmp_path)
    result = _run_deploy(script, elsewhere, env)
    assert result.returncode == 0, result.stderr
    assert log.read_text().split("|")[1].split() == [
        "-m", "pip", "install", "--no-deps", "--editable", str(checkout.resolve())]


@pytest.mark.parametrize("source_dir", [None, "not-a-checkout"])
def test_post_deploy_without_a_checkout_fails_saying_what_to_set(tmp_path, source_dir):
    workdir = tmp_path / "work"
    script = _deploy_copy(workdir)
    env, log = _fake_python(tmp_path)
    if source_dir:
        (tmp_path / source_dir).mkdir()
        env["SEATHRU_SOURCE_DIR"] = str(tmp_path / source_dir)
    result = _run_deploy(script, workdir, env)
    assert result.returncode != 0
    assert "SEATHRU_SOURCE_DIR" in result.stderr and "seathru-pipeline" in result.stderr
    assert not log.exists(), "pip ran without a checkout"


def test_the_workflow_tells_post_deploy_its_checkout(tmp_path):
    code = (
        "import os\n"
        "from pathlib import Path\n"
        "from snakemake.api import SnakemakeApi\n"
        "from snakemake.settings.types import (ConfigSettings, DAGSettings, OutputSettings,\n"
        "                                      ResourceSettings)\n"
        f"repo = Path({str(REPO_ROOT)!r})\n"
        "with SnakemakeApi(OutputSettings()) as api:\n"
        "    api.workflow(resource_settings=ResourceSettings(cores=1),\n"
        "                 config_settings=ConfigSettings(configfiles=[repo / 'config/config.yaml']),\n"
        "                 snakefile=repo / 'workflow/Snakefile', workdir=repo).dag(DAGSettings())\n"
        "print('SOURCE=' + os.environ.get('SEATHRU_SOURCE_DIR', ''))\n")
    env = {k: v for k, v in os.environ.items() if k != "SEATHRU_SOURCE_DIR"}
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"SOURCE={REPO_ROOT.resolve()}" in result.stdout.splitlines()


def test_license_file_matches_pyproject():
    if tomllib is None:
        pytest.skip("tomllib needs Python 3.11")
    licence = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["license"]
    name = licence["text"] if isinstance(licence, dict) else licence
    assert (REPO_ROOT / "LICENSE").read_text().splitlines()[0] == f"{name} License"


def test_test_configuration_plans_every_stage_of_its_datasets(tmp_path):
    """`.test/` is the tiny end-to-end configuration (`snakemake --directory .test`)."""
    workdir = tmp_path / "test-config"
    shutil.copytree(REPO_ROOT / ".test", workdir,
                    ignore=shutil.ignore_patterns("results", "logs", ".snakemake"))
    result = snakemake("-n", "--cores", "1", "--directory", str(workdir))
    assert result.returncode == 0, result.stderr[-2000:]
    sheet = (workdir / "config" / "datasets.tsv").read_text()
    simulated = sheet.count("\tsimulated\t")
    datasets = len([line for line in sheet.splitlines()[1:] if line and not line.startswith("#")])
    for rule, count in (("simulate", simulated), ("ingest", datasets), ("train", datasets),
                        ("report", 1)):
        assert re.search(rf"^{rule}\s+{count}$", result.stdout, re.M), (rule, result.stdout)


def test_each_source_reaches_its_images_and_poses(tmp_path):
    """The flags the rules pass per source: posed layouts go to ingest as --layout (the
    ingest.images option chooses their image folder) and to poses as their reader."""
    rows = []
    for dataset, source, options in (("dive_raw", "raw", ""), ("dive_jpg", "images", ""),
                                     ("release", "llff", ""),
                                     ("llff4", "llff", "ingest.images=images_4"),
                                     ("ns", "nerfstudio", ""), ("cm", "colmap", ""),
                                     ("sim", "simulated", ""),
                                     ("sim_jpeg", "simulated", "ingest.images=jpeg")):
        folder = tmp_path / dataset
        folder.mkdir()
        rows.append(f"{dataset}\t{source}\t{'' if source == 'simulated' else folder}\t{options}")
    sheet = _sheet(tmp_path, rows)
    result = snakemake("-n", "-p", "--cores", "1", "--forceall", "--config", f"datasets={sheet}")
    assert result.returncode == 0, result.stderr[-3000:]
    commands = _shell_commands(result.stdout)

    def argv(step, dataset):
        return shlex.split(commands[(step, dataset)].split(" > ")[0])

    def value(args, flag):
        return args[args.index(flag) + 1] if flag in args else None

    for dataset, layout, reader in (("release", "llff", "llff"), ("llff4", "llff", "llff"),
                                    ("ns", "nerfstudio", "nerfstudio"),
                                    ("cm", "colmap", "colmap-model")):
        ingest, poses = argv("ingest", dataset), argv("poses", dataset)
        assert value(ingest, "--layout") == layout and "--subdir" not in ingest, ingest
        assert value(ingest, "--input") == str(tmp_path / dataset)
        assert value(poses, "--source") == reader
        assert value(poses, "--source-dir") == str(tmp_path / dataset)
    assert value(argv("ingest", "llff4"), "--images") == "images_4"
    for dataset in ("dive_raw", "dive_jpg"):
        assert "--layout" not in argv("ingest", dataset)
        assert value(argv("poses", dataset), "--source") == "colmap"
    assert value(argv("ingest", "dive_raw"), "--kind") == "raw"
    assert value(argv("ingest", "sim"), "--subdir") == "raw"
    assert value(argv("ingest", "sim"), "--kind") == "raw"
    # a simulated dive trained on its camera JPEGs (their kind detected: sRGB)
    assert value(argv("ingest", "sim_jpeg"), "--subdir") == "jpeg"
    assert "--kind" not in argv("ingest", "sim_jpeg")


def test_the_community_protocol_ingests_at_full_resolution_unless_told(tmp_path):
    """ingest.max_size downscales large photographs by default; NerfBaselines' protocol
    compares with the stored images as they are, so a row asking for it ingests them whole."""
    rows = []
    for dataset, options in (("plain", ""), ("protocol", "evaluate.protocol=nerfbaselines"),
                             ("sized", "evaluate.protocol=nerfbaselines; ingest.max_size=800")):
        (tmp_path / dataset).mkdir()
        rows.append(f"{dataset}\tllff\t{tmp_path / dataset}\t{options}")
    result = snakemake("-n", "-p", "--cores", "1", "--forceall", "--config",
                       f"datasets={_sheet(tmp_path, rows)}")
    assert result.returncode == 0, result.stderr[-3000:]
    commands = _shell_commands(result.stdout)
    assert "--max-size" not in commands[("ingest", "plain")]
    assert "--max-size 0 " in commands[("ingest", "protocol")]
    assert "--max-size 800 " in commands[("ingest", "sized")]
    helpers = workflow_helpers()
    assert helpers["ingest_for_protocol"]({"workers": 2}, {"protocol": "seathru"}) == \
        {"workers": 2}


def test_paths_with_spaces_reach_every_step_whole(tmp_path):
    """A dive folder named as people name them ("Dive 3 - reef") and a results folder with a
    space in it: every path of every step's shell line parses back whole."""
    folder = tmp_path / "Dive 3 - reef"
    folder.mkdir()
    results, logs = tmp_path / "my results", tmp_path / "my logs"
    sheet = _sheet(tmp_path, [f"reef\timages\t{folder}\t", f"cm\tcolmap\t{folder}\t",
                              "sim\tsimulated\t\t"])
    result = snakemake("-n", "-p", "--cores", "1", "--forceall", "--config",
                       f"datasets={sheet}", f"results={results}", f"logs={logs}")
    assert result.returncode == 0, result.stderr[-3000:]
    commands = _shell_commands(result.stdout)
    assert {step for step, _ in commands} >= {"ingest", "poses", "train", "render", "evaluate",
                                              "report"}, sorted(commands)
    for (step, dataset), command in commands.items():
        line, _, redirect = command.partition(" > ")
        argv = shlex.split(line)
        log = shlex.split(redirect)
        assert len(log) == 2 and log[1] == "2>&1" and log[0].startswith(str(logs)), command
        out = argv[argv.index("--out") + 1]
        assert out.startswith(str(results)), (step, out)
        for flag in ("--input", "--ingest", "--cameras", "--model", "--renders", "--train-dir",
                     "--checkpoint-dir", "--poses", "--results", "--logs"):
            if flag in argv:
                value = argv[argv.index(flag) + 1]
                assert value.startswith((str(results), str(folder), str(logs))), (step, value)
    ingest = shlex.split(commands[("ingest", "reef")].split(" > ")[0])
    assert ingest[ingest.index("--input") + 1] == str(folder)
    poses = shlex.split(commands[("poses", "cm")].split(" > ")[0])
    assert poses[poses.index("--source-dir") + 1] == str(folder)


def test_sheet_paths_read_home_and_environment_variables(tmp_path, monkeypatch):
    """``~/dives/reef`` and ``$SCRATCH/reef`` in the sheet's path column, as a shell reads
    them; a variable that is not set is named in the error."""
    home, scratch = tmp_path / "home", tmp_path / "scratch"
    (home / "dives" / "reef").mkdir(parents=True)
    (scratch / "reef").mkdir(parents=True)
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("SCRATCH", str(scratch))
    monkeypatch.delenv("SEATHRU_NOT_SET", raising=False)
    sheet = _sheet(tmp_path, ["home\timages\t~/dives/reef\t", "cluster\traw\t$SCRATCH/reef\t"])
    result = snakemake("-n", "-p", "--cores", "1", "--forceall", "--config", f"datasets={sheet}")
    assert result.returncode == 0, result.stderr[-3000:]
    commands = _shell_commands(result.stdout)
    for dataset, folder in (("home", home / "dives" / "reef"), ("cluster", scratch / "reef")):
        ingest = shlex.split(commands[("ingest", dataset)].split(" > ")[0])
        assert ingest[ingest.index("--input") + 1] == str(folder)
    unset = _sheet(tmp_path, ["lost\timages\t$SEATHRU_NOT_SET/reef\t"])
    result = snakemake("-n", "--cores", "1", "--config", f"datasets={unset}")
    assert result.returncode != 0
    assert "environment variable SEATHRU_NOT_SET is not set" in result.stdout + result.stderr


def test_a_sheet_path_to_an_archive_or_a_file_is_refused_saying_so(tmp_path):
    archive, image = tmp_path / "dive.zip", tmp_path / "one.jpg"
    archive.write_bytes(b"PK\x03\x04")
    image.write_bytes(b"\xff\xd8")
    for path, expected in ((archive, "is an archive: unpack it"), (image, "is a file: give")):
        sheet = _sheet(tmp_path, [f"d1\timages\t{path}\t"])
        result = snakemake("-n", "--cores", "1", "--config", f"datasets={sheet}")
        assert result.returncode != 0
        assert f"field 'path': '{path}' {expected}" in result.stdout + result.stderr


def test_steps_find_the_seathru_command_without_an_activated_environment(tmp_path):
    """`.venv/bin/snakemake` with the environment not on PATH: the steps still find `seathru`
    (they failed with "seathru: command not found")."""
    import numpy as np
    from PIL import Image

    images = tmp_path / "two"
    images.mkdir()
    for name in ("a.png", "b.png"):
        Image.fromarray(np.full((16, 16, 3), 90, np.uint8)).save(images / name)
    sheet = tmp_path / "sheet.tsv"
    sheet.write_text(f"dataset\tsource\tpath\toptions\tsweep\ntwo\timages\t{images}\t\t\n")
    bin_dir = str(Path(sys.executable).parent)
    path = os.pathsep.join(p for p in os.environ["PATH"].split(os.pathsep)
                           if p and Path(p).resolve() != Path(bin_dir).resolve())
    result = subprocess.run(
        [sys.executable, "-m", "snakemake",
         "--snakefile", str(REPO_ROOT / "workflow" / "Snakefile"), "--directory", str(tmp_path), "--configfile", str(REPO_ROOT / "config" / "config.yaml"),
         "--config", f"datasets={sheet}", "--cores", "1", "results/two/ingest"],
        cwd=tmp_path, env=dict(os.environ, PATH=path), capture_output=True, text=True,
        timeout=300)
    log = (tmp_path / "logs" / "two" / "ingest.log").read_text()
    assert "command not found" not in log + result.stderr
    assert "usable image(s)" in log, log   # the step ran and refused two images
