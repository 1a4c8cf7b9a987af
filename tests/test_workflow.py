"""The Snakemake workflow: dry runs, lint, profiles, sheet validation, environment pins."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO_ROOT

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
        (["d 1\tsimulated\t\t"], None, "field 'dataset'"),
        (["d1\tsimulated\t\t", "d1\tsimulated\t\t"], None, "appears more than once"),
    ],
)
def test_malformed_sheet_is_refused_before_any_job(tmp_path, rows, header, expected):
    sheet = _sheet(tmp_path, rows, header or "dataset\tsource\tpath\toptions")
    result = snakemake("-n", "--cores", "1", "--config", f"datasets={sheet}")
    assert result.returncode != 0
    output = result.stdout + result.stderr
    assert re.search(expected, output), output[-2000:]


def test_unknown_option_of_an_existing_step_is_refused(tmp_path):
    from seathru.cli import build_parser

    steps = build_parser()._subparsers._group_actions[0].choices
    step = next(iter(steps))
    sheet = _sheet(tmp_path, [f"d1\tsimulated\t\t{step}.no_such_flag=1"])
    result = snakemake("-n", "--cores", "1", "--config", f"datasets={sheet}")
    assert result.returncode != 0
    assert f"{step}.no_such_flag is not an option of 'seathru {step}'" in result.stdout + result.stderr


def test_wrong_config_value_is_refused():
    result = snakemake("-n", "--cores", "1", "--config", "resources={default: {threads: 0}}")
    assert result.returncode != 0
    assert "threads" in result.stdout + result.stderr


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
