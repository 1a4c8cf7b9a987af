"""Shared fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


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
