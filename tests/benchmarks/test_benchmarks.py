"""Every benchmark still starts: its imports resolve and its options parse (`--help`)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.support.paths import REPO

BENCHMARKS = sorted((REPO / "benchmarks").glob("bench_*.py"))


def test_there_are_benchmarks():
    assert len(BENCHMARKS) >= 9


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.name)
def test_benchmark_starts(script):
    run = subprocess.run(
        [sys.executable, str(script), "--help"], capture_output=True, text=True, check=False
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "usage:" in run.stdout
