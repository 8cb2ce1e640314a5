"""Shared fixtures: the real test data in ``../shared/data`` (never copied into the repository)."""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Root of the shared real data (may be absent on a user's machine)."""
    return SHARED_DATA


@pytest.fixture(scope="session")
def shared_subdir(shared_data):
    """``shared_subdir('davis2016')`` -> that folder, or skip the test saying which is missing."""

    def get(name: str) -> Path:
        folder = shared_data / name
        if not folder.is_dir():
            pytest.skip(f"real test data {folder} is absent")
        return folder

    return get
