"""Fixtures every test folder shares: the real scan and its labels in `tests/data`."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.paths import data_path


@pytest.fixture(scope="session")
def real_scan_path() -> Path:
    """The real SemanticKITTI scan (123,389 points)."""
    return data_path("semantickitti-scan", "000000.bin")


@pytest.fixture(scope="session")
def real_label_path() -> Path:
    """Ground-truth labels of the real scan."""
    return data_path("semantickitti-scan", "000000.label")
