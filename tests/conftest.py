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


@pytest.fixture(autouse=True)
def _denormals_kept():
    """Each test starts with IEEE denormals, whatever an in-process step set before it.

    The train step flushes denormals to zero for speed; a leak into later tests makes
    hypothesis refuse its float strategies, so the state is pinned per test.
    """
    import torch

    torch.set_flush_denormal(False)
    yield
    torch.set_flush_denormal(False)
