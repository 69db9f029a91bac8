"""`pip install .` is the library and its light commands; Ray, the gateway, ONNX and the hub are
extras, and a command whose extra is missing stops with one line naming it.

The light runs happen in a subprocess where every optional package is made unimportable (None in
`sys.modules`), as in an environment without the extras.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

from tests.support.paths import REPO, data_path

#: The top-level modules of every optional extra (and what they pull in), blocked in the runs.
BLOCKED = (
    "ray",
    "fastapi",
    "starlette",
    "uvicorn",
    "pydantic",
    "pydantic_settings",
    "onnx",
    "onnxscript",
    "onnxruntime",
    "huggingface_hub",
    "pypcd4",
    "laspy",
    "lazrs",
    "rosbags",
    "rclpy",
    "sensor_msgs",
    "diagnostic_msgs",
)
#: Runs the `main` of a module with the named modules made unimportable.
RUNNER = """\
import importlib, sys
for name in sys.argv[1].split(","):
    sys.modules[name] = None
sys.exit(importlib.import_module(sys.argv[2]).main(sys.argv[3:]))
"""


def rangeret_without_extras(
    *argv: str, cwd: Path, entry: str = "rangeret.cli.main"
) -> subprocess.CompletedProcess:
    """`rangeret ARGV` (or another entry module's `main`) in a fresh interpreter where none of
    the extras can be imported."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1"}
    return subprocess.run(
        [sys.executable, "-c", RUNNER, ",".join(BLOCKED), entry, *argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def real_scan_tree(root: Path) -> Path:
    """A SemanticKITTI tree whose sequence 08 holds the real scan of tests/data and its labels."""
    for kind, name in (("velodyne", "000000.bin"), ("labels", "000000.label")):
        folder = root / "sequences" / "08" / kind
        folder.mkdir(parents=True)
        (folder / name).write_bytes(data_path("semantickitti-scan", name).read_bytes())
    return root


@pytest.mark.slow
def test_predict_and_evaluate_run_without_any_extra(tmp_path):
    dataset = real_scan_tree(tmp_path / "dataset")
    pred, report = tmp_path / "pred", tmp_path / "report.json"
    run = rangeret_without_extras(
        "predict", "--dataset", str(dataset), "--sequences", "08", "--out", str(pred), "-q",
        cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "1 scans: 1 written, 0 already done, 0 failed" in run.stdout
    labels = pred / "sequences" / "08" / "predictions" / "000000.label"
    points = data_path("semantickitti-scan", "000000.bin").stat().st_size // 16
    assert labels.stat().st_size == 4 * points

    run = rangeret_without_extras(
        "evaluate", "--dataset", str(dataset), "--predictions", str(pred), "--sequences", "08",
        "--json", str(report), "--plots", str(tmp_path / "plots"), "-q",
        cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert re.search(r"^mIoU\s+\d+\.\d\d$", run.stdout, flags=re.M), run.stdout
    assert f"report: {report}" in run.stdout
    doc = json.loads(report.read_text())
    assert doc["num_scans"] == 1 and doc["num_points"] == points
    assert 0.0 <= doc["miou"] <= 1.0 and doc["profile"] == "semantickitti"
    assert (tmp_path / "plots" / "confusion.png").stat().st_size > 0


def _line(feature: str, extra: str) -> str:
    return f"{feature} needs the {extra} extra: pip install 'rangeret-service[{extra}]'\n"


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["serve"], _line("rangeret serve", "gateway")),
        (["serve", "--port", "8123", "--no-knn"], _line("rangeret serve", "gateway")),
        (["-q", "demo", "--out", "demo"], _line("rangeret demo", "ray")),
        (["ros2", "--rgb"], _line("rangeret ros2", "ros2")),
        (["export", "--out", "net.onnx"], _line("rangeret export", "onnx")),
        (
            ["train", "--dataset", "d", "--model", "rangeret-thesis", "--out", "o", "--ray"],
            _line("rangeret train --ray", "ray"),
        ),
        (
            [
                "predict",
                "--dataset",
                "d",
                "--split",
                "valid",
                "--out",
                "p",
                "--backend",
                "onnxruntime",
            ],
            _line("--backend onnxruntime", "onnx"),
        ),
        (
            ["weights", "download", "rangeret-kitti-657"],
            _line("downloading rangeret-kitti-657", "hub"),
        ),
    ],
    ids=[
        "serve",
        "serve-options",
        "demo",
        "ros2",
        "export",
        "train-ray",
        "onnxruntime",
        "weights-download",
    ],
)
def test_a_command_without_its_extra_stops_with_one_line(tmp_path, argv, expected):
    run = rangeret_without_extras(*argv, cwd=tmp_path)
    assert (run.returncode, run.stderr) == (1, expected), run.stdout
    assert list(tmp_path.iterdir()) == []  # nothing was written


def test_weights_list_runs_without_the_hub(tmp_path):
    run = rangeret_without_extras("weights", "list", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert re.search(r"^rangeret-kitti-657\s.*\sno\s", run.stdout, flags=re.M), run.stdout


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_the_all_extra_holds_every_other_extra_but_dev():
    extras = _pyproject()["project"]["optional-dependencies"]
    (requirement,) = extras["all"]
    match = re.fullmatch(r"rangeret-service\[([a-z0-9,_-]+)\]", requirement.replace(" ", ""))
    assert match, requirement
    assert sorted(match.group(1).split(",")) == sorted(set(extras) - {"all", "dev"})


def test_the_default_install_is_the_light_library():
    from rangeret.extras import EXTRA_MODULES

    project = _pyproject()["project"]
    names = {re.split(r"[<>=\[ ]", r, maxsplit=1)[0].lower() for r in project["dependencies"]}
    assert names == {"numpy", "torch", "pyyaml", "tqdm", "matplotlib", "scipy"}
    extras = project["optional-dependencies"]
    assert set(EXTRA_MODULES) <= set(extras) - {"all", "dev"}
    assert "ray[default,data,serve]==2.60.0" in extras["ray"]


#: Extras the cluster image leaves out, and why.
NOT_IN_IMAGE = {"ros2": "the ROS 2 node runs on the robot, beside its own ROS install"}


def test_the_environments_install_every_extra():
    """The Makefile's virtual environment installs `.[all,dev]`; the image (which installs the
    project with --no-deps) names every requirement of every extra but dev and those it leaves
    out (NOT_IN_IMAGE) in its pip commands or the requirements files they read, and the leaving
    out is real."""
    assert "pip install -qq -e '.[all,dev]'" in (REPO / "Makefile").read_text()
    dockerfile = (REPO / "deploy" / "Dockerfile").read_text().replace("\\\n", " ")
    commands = re.findall(r"pip install[^&]*", dockerfile)
    files = [REPO / f for c in commands for f in re.findall(r"-r\s+(\S+)", c)]
    assert files, "the image installs its requirements from a file"
    lines = [line.split("#")[0].strip() for f in files for line in f.read_text().splitlines()]
    installed = " ".join([*commands, *(line for line in lines if line)])
    extras = _pyproject()["project"]["optional-dependencies"]
    for extra, requirements in extras.items():
        if extra in ("all", "dev"):
            continue
        for requirement in requirements:
            name = re.split(r"[<>=\[ ]", requirement, maxsplit=1)[0]
            found = re.search(rf"(^|[\s\"]){re.escape(name)}([\s\"\[]|$)", installed)
            assert bool(found) is (extra not in NOT_IN_IMAGE), (extra, name)


def test_the_gateway_module_without_its_extra_stops_with_one_line(tmp_path):
    """`python -m service`, the gateway without the `rangeret` command, says the same line."""
    run = rangeret_without_extras("--port", "1", cwd=tmp_path, entry="service.__main__")
    assert (run.returncode, run.stderr) == (1, _line("python -m service", "gateway")), run.stdout
