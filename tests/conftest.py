"""Shared test fixtures: repository paths and the shared data folder."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    return SHARED


@pytest.fixture(scope="session")
def real_data_dir() -> Path:
    d = SHARED / "data" / "real"
    if not d.is_dir():
        pytest.skip(f"shared real data not found at {d}")
    return d

