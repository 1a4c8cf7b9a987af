"""Shared fixtures."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def _skip_an_unreachable_slurm_controller() -> None:
    """Where a SLURM client is installed but its controller is down, put an ``scontrol`` that
    fails at once first on PATH. The SLURM executor plugin runs ``scontrol show config`` when
    Snakemake imports it, and against a dead controller that waits 9-10 s: every Snakemake run
    of the suite paid it (the suite took 19 min instead of 11). ``scontrol ping`` answers at
    once either way; with a live controller nothing changes."""
    scontrol = shutil.which("scontrol")
    if scontrol is None:
        return
    try:
        if subprocess.run([scontrol, "ping"], capture_output=True, timeout=5).returncode == 0:
            return
    except (OSError, subprocess.TimeoutExpired):
        pass
    folder = Path(tempfile.mkdtemp(prefix="seathru_tests_no_slurm_"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    (folder / "scontrol").write_text("#!/bin/sh\nexit 1\n")
    (folder / "scontrol").chmod(0o755)
    os.environ["PATH"] = f"{folder}{os.pathsep}{os.environ.get('PATH', '')}"


_skip_an_unreachable_slurm_controller()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Slow tests first, SLURM's first of all. ``make test`` runs the files in two processes in
    collection order (``--no-loadscope-reorder``): the long files start at once instead of
    finishing alone, and the SLURM run, which mostly waits on the queue, overlaps the others."""
    items.sort(key=lambda item: (item.get_closest_marker("slow") is None,
                                 "test_slurm.py" not in item.nodeid))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real test data in ../shared/data; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (clone the project beside shared/)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT



COMMON_SMK = REPO_ROOT / "workflow" / "rules" / "common.smk"
WORKFLOW_GLUE_MARKER = "# ====="


def workflow_helpers() -> dict:
    """The plain-Python helpers of workflow/rules/common.smk (everything above its "workflow
    glue" line, which needs none of Snakemake's globals), as a namespace."""
    text = COMMON_SMK.read_text()
    head, marker, _ = text.partition(WORKFLOW_GLUE_MARKER)
    assert marker, f"{COMMON_SMK}: no '{WORKFLOW_GLUE_MARKER}... workflow glue' line"
    namespace: dict = {"__name__": "common_smk"}
    exec(compile(head, str(COMMON_SMK), "exec"), namespace)
    return namespace
