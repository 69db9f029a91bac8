"""The README's `serve deploy deploy/serve.yaml`: the shipped CPU Serve config deploys on a real
`ray start --head` (token authentication, stopped by its own process group) and labels a scan as
`rangeret predict` does, with only the values an operator changes replaced: the checkpoint (a
local file for the published model's name), its resolution, and a free port for Serve's proxy."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml

from rangeret.cli.main import main as rangeret_main
from rangeret.io.scans import read_labels
from tests.support.paths import REPO
from tests.support.workers import build_tree, free_ports, ray_node, serve_deploy, small_weights
from workers.scan_wire import decode_labels

pytestmark = pytest.mark.slow

#: The file the README's `serve deploy` names, which the repository must hold.
CONFIG = REPO / re.search(r"^serve deploy (\S+) ", (REPO / "README.md").read_text(), re.M).group(1)


def _deployed_config(tmp: Path, weights: Path, port: int) -> Path:
    """deploy/serve.yaml with the small weights for the published name and a free port."""
    config = yaml.safe_load(CONFIG.read_text())
    (app,) = config["applications"]
    assert app["args"]["checkpoint"] == "rangeret-kitti-657" and app["args"]["device"] == "cpu"
    app["args"] |= {"checkpoint": str(weights), "height": 32, "width": 256}
    config["http_options"]["port"] = port
    path = tmp / "serve.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_the_shipped_serve_config_deploys_and_labels_a_scan(tmp_path):
    pytest.importorskip("ray")
    weights = small_weights(tmp_path)
    (port,) = free_ports(1)
    path = _deployed_config(tmp_path, weights, port)
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=0)
    argv = ["predict", "-q", "--dataset", str(data), "--sequences", "08"]
    argv += ["--out", str(tmp_path / "pred"), "--checkpoint", str(weights)]
    assert rangeret_main([*argv, "--height", "32", "--width", "256", "--device", "cpu"]) == 0
    scan = next((data / "sequences" / "08" / "velodyne").glob("*.bin"))
    expected = read_labels(tmp_path / "pred" / "sequences" / "08" / "predictions" / "000000.label")
    url = f"http://127.0.0.1:{port}/rangeret"
    with ray_node(tmp_path, num_cpus=2) as head:
        serve_deploy(head, path, [url], timeout=180)
        answer = httpx.post(
            f"{url}/scans",
            content=scan.read_bytes(),
            headers={"Content-Type": "application/octet-stream"},
            timeout=60,
        )
    assert answer.status_code == 200, answer.text
    labels = decode_labels(answer.content, answer.headers, len(expected)).labels
    assert np.array_equal(labels, expected)
