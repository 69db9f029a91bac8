"""`rangeret demo` as `make demo` runs it, in a process of its own with a home folder of its own:
Ray's token and logs stay in the run's folder (none in the home folder, no session folder left in
/tmp), the output says where they are, and the notes suggest weights the profile can run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.paths import REPO

pytestmark = pytest.mark.slow


def test_the_nuscenes_demo_keeps_rays_files_in_its_folder_and_hints_nuscenes_weights(tmp_path):
    pytest.importorskip("ray")
    home, out = tmp_path / "home", tmp_path / "demo"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("RAY_", "RANGERET_"))}
    env["HOME"] = str(home)
    command = ["demo", "-q", "--profile", "nuscenes", "--out", str(out)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "rangeret.cli.main", *command],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    printed, errors = proc.communicate(timeout=300)
    assert proc.returncode == 0, errors[-3000:]
    assert not (home / ".ray").exists()
    assert not Path(f"/tmp/rangeret-ray-{proc.pid}").exists()
    listed = dict(
        line.strip().split(":", 1) for line in printed.splitlines() if line.startswith("  Ray's")
    )
    token = Path(listed["Ray's token (this run's only)"].strip())
    logs = Path(listed["Ray's own logs"].strip())
    assert token.parent == logs.parent == out / "ray"
    assert token.stat().st_mode & 0o077 == 0 and len(token.read_text()) == 64
    assert (logs / "driver-stderr.log").is_file()
    # The hints are for weights that run on nuScenes, never SemanticKITTI's published model.
    assert "rangeret-kitti-657" not in printed
    note = next(line for line in printed.splitlines() if line.startswith("Note: "))
    assert "demo weights" in note and "--profile nuscenes" in note
