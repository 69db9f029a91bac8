"""Every command of the README's `bash` blocks that starts with `rangeret`, `python -m workers.` or
`make`, read from the README and run as written, each in a process of its own, in the README's
order, on small simulated trees; the gateway's commands are checked with the README's own `curl`
lines.

Only the README's placeholders are replaced (ROOT: a simulated SemanticKITTI tree, or a PandaSet
one for the PandaSet fine-tuning; PRED, DIR, OUT, plots/: folders; `rangeret-kitti-657`,
`ckpt.pt` and CHECKPOINT: a small published-layout state_dict of 32 x 256, since the model hub is
not reached; the scan and label files of `view`; `...` of the ONNX prediction: the arguments of
the prediction before it; port 8000: a free port), optional `[...]` parts are run with their
placeholders filled in, and options that keep the runs small are added (the small weights'
resolution, one step of a one-block network, no loader workers, the CPU). The lines of
`SKIPPED` need the internet or a Ray cluster, or run test suites; the test checks that they are
exactly the lines it does not run."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml

from rangeret.cli.main import main
from rangeret.dataset.profiles import load_profile
from rangeret.io.scans import read_scan
from rangeret.sim import SensorConfig, simulate_dataset
from tests.support.doc_commands import ONE_STEP, SMALL_NET, code_commands, run_rangeret
from tests.support.gateway import Gateway, free_port, wait_healthy
from tests.support.paths import REPO
from tests.support.point_files import pcd_bytes
from tests.support.workers import small_weights

pytestmark = pytest.mark.slow

README = REPO / "README.md"
PROFILES = REPO / "rangeret" / "data" / "profiles"
#: The command lines the README's `bash` blocks hold that this test runs or skips.
PREFIXES = ("rangeret ", "python -m workers.", "make ")
#: The lines not run here, each with its reason.
SKIPPED = {
    "make demo": "starts a local Ray cluster for minutes; tests/workers/test_demo.py runs the demo",
    "make test": "the whole test suite, this test included",
    "make check": "the test suite but for its slow tests, minutes long",
    "rangeret weights download rangeret-kitti-657 [--to DIR]": "needs the model hub",
    "python -m workers.predict_job --dataset ROOT --split valid --out PRED --report report.json "
    "--checkpoint ...": "starts a Ray cluster; tests/workers run the job",
    "rangeret train --dataset ROOT --model rangeret-thesis --out DIR --ray --workers 4": (
        "Ray Train with four workers needs a Ray cluster"
    ),
    "rangeret serve --checkpoint rangeret-kitti-657 --serve-url http://HEAD:8000/rangeret "
    "--jobs-address http://HEAD:8265": "needs a Ray cluster running Serve and the jobs API",
}
#: The resolution of the small weights, which published files do not record.
SMALL_RES = ["--height", "32", "--width", "256"]
#: The README's names of the published weights, all replaced by the small weights.
WEIGHTS = ("rangeret-kitti-657", "ckpt.pt", "CHECKPOINT")
#: The scan the gateway's first `curl` lines send (a PandaSet scan replaces it for `?model=panda`).
KITTI_SCAN = "kitti/sequences/08/velodyne/000000.bin"
#: The file name of the small weights.
SMALL_WEIGHTS = "weights.pt"


def expand(command: str, substitutions: dict[str, str]) -> list[str]:
    """The words of a README line with its optional `[...]` parts kept (brackets removed) and its
    placeholders replaced (a placeholder may stand for several words, separated by spaces)."""
    words = shlex.split(command.replace("[", "").replace("]", ""))
    return [part for word in words for part in substitutions.get(word, word).split(" ")]


def small_options(words: list[str]) -> list[str]:
    """What keeps a README command's run small: the small weights' resolution where they are
    named, one training step of a one-block network, no progress bars, and a test set of one scan
    (`--allow-partial`, which the README names for tests)."""
    args = words[1:]
    extra: list[str] = []
    if args[0] in ("predict", "adapt", "simulate", "train"):
        extra.append("-q")
    named = {args[i + 1] for i, w in enumerate(args[:-1]) if w in ("--checkpoint", "--init-from")}
    if any(Path(name).name == SMALL_WEIGHTS for name in named):
        extra += SMALL_RES
    if args[0] == "train" and "--config" not in args:
        extra += ONE_STEP + ([] if "--init-from" in args else SMALL_NET)
    if args[0] in ("submission", "validate-submission"):
        extra.append("--allow-partial")
    if args[0] == "simulate":
        extra += ["--beams", "32", "--azimuth-steps", "256"]
    return extra


def run(command: str, substitutions: dict[str, str]) -> str:
    """One README command in a process of its own, placeholders replaced, small-run options
    added; its standard output (written to the file a `>` names)."""
    words = expand(command, substitutions)
    if ">" in words:
        cut = words.index(">")
        words, redirect = words[:cut], words[cut:]
    else:
        redirect = []
    return run_rangeret([*words[1:], *small_options(words), *redirect], command)


def shell(script: str, port: int) -> str:
    """README `curl` lines run by bash against the gateway on `port`; their standard output."""
    script = script.replace("localhost:8000", f"127.0.0.1:{port}")
    done = subprocess.run(
        ["bash", "-ec", script], capture_output=True, text=True, errors="replace", timeout=120
    )
    assert done.returncode == 0, f"{script}\n{done.stderr[-2000:]}"
    return done.stdout


def serve(command: str, substitutions: dict[str, str], log: Path) -> Gateway:
    """A README `rangeret serve` line as a running gateway on a free port instead of 8000."""
    port = free_port()
    words = expand(command, substitutions)
    args = [*words[1:], *small_options(words)]
    if "--port" in args:
        args[args.index("--port") + 1] = str(port)
    else:
        args += ["--port", str(port)]
    env = {k: v for k, v in os.environ.items() if not k.startswith("RANGERET_")}
    env["RANGERET_STATE_DIR"] = str(log.parent / f"state-{port}")
    with open(log, "ab") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "rangeret.cli.main", *args],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    return wait_healthy(Gateway(f"http://127.0.0.1:{port}", proc, log))


def block_after(text: str, command: str) -> str:
    """The lines of the README block holding `command` that follow it (its `curl` lines)."""
    block = next(b for b in re.findall(r"```bash\n(.*?)```", text, flags=re.S) if command in b)
    return block.split(command, 1)[1].split("\n", 1)[1]


def make_data(tmp: Path) -> None:
    """The trees, weights and files the README's placeholders stand for, under `tmp`."""
    kitti, panda = load_profile("semantickitti"), load_profile("pandaset")
    small = SensorConfig(beams=32, azimuth_steps=256)
    names = [*kitti.splits["train"], *kitti.splits["valid"], "11", "42", "43"]
    sequences = dict.fromkeys(names, 1)
    labelled = [s for s in sequences if s != "11"]
    simulate_dataset(tmp / "kitti", sequences, labelled, sensor=small, seed=3, profile=kitti)
    pandas = dict.fromkeys([*panda.splits["train"], *panda.splits["valid"]], 1)
    simulate_dataset(tmp / "panda", pandas, sensor=small, seed=4, profile=panda)
    shutil.copy(small_weights(tmp), tmp / SMALL_WEIGHTS)
    scan = tmp / KITTI_SCAN
    shutil.copy(scan, tmp / "000000.bin")
    (tmp / "scan.pcd").write_bytes(pcd_bytes(read_scan(scan).astype(np.float32), "binary"))
    with zipfile.ZipFile(tmp / "sequence.zip", "w") as archive:
        archive.write(scan, "sequences/08/velodyne/000000.bin")
    mine = yaml.safe_load((PROFILES / "semantickitti.yaml").read_text())
    mine["name"] = "my-sensor"
    mine["sensor"].update(height=16, width=128)
    (tmp / "my-sensor.yaml").write_text(yaml.safe_dump(mine, sort_keys=False))
    identity = {raw: raw for raw in kitti.labels.raw_names}
    (tmp / "map.yaml").write_text(yaml.safe_dump(identity))


def test_every_readme_command_runs_as_written(tmp_path, monkeypatch):
    text = README.read_text()
    lines = list(dict.fromkeys(code_commands(text, PREFIXES, language="bash")))
    monkeypatch.chdir(tmp_path)
    make_data(tmp_path)
    weights = str(tmp_path / SMALL_WEIGHTS)
    substitutions = {
        **dict.fromkeys(WEIGHTS, weights),
        "ROOT": "kitti",
        "PRED": "pred",
        "DIR": "run",
        "OUT": "adapted",
        "N": "1",
        "H": "32",
        "W": "256",
        "DX": "0.5",
        "DY": "0",
        "DZ": "0.1",
        "MAP.yaml": "map.yaml",
        "TEXT": "small-run",
        "PRED/.../000000.label": "pred/sequences/08/predictions/000000.label",
        "labels/000000.label": "kitti/sequences/08/labels/000000.label",
        "pred.label": "pred/sequences/08/predictions/000000.label",
        "gt.label": "kitti/sequences/08/labels/000000.label",
    }
    ran: list[str] = []
    outputs: dict[str, str] = {}
    log = tmp_path / "serve.log"
    for line in lines:
        if line in SKIPPED:
            continue
        ran.append(line)
        subs = dict(substitutions)
        if line.startswith("rangeret compare"):
            for name in ("baseline.json", "no-knn.json", "no-tta.json"):
                shutil.copy("report.json", name)
        elif line.startswith("rangeret submission"):
            argv = ["predict", "-q", "--dataset", "kitti", "--sequences", "11", "--out", "pred"]
            assert main([*argv, "--checkpoint", weights, *SMALL_RES]) == 0
        elif line.startswith("rangeret simulate"):
            subs["ROOT"] = "simulated"
        elif "--print-config" in line:
            subs["DIR"] = "run-config"
        elif "--profile pandaset" in line:
            subs.update(ROOT="panda", DIR="panda-run")
        elif line.startswith("rangeret predict ..."):
            subs["..."] = f"--dataset kitti --split valid --out pred-onnx --checkpoint {weights}"
        if line.startswith("rangeret serve"):
            if "--models" in line:
                models = {
                    "default": "kitti",
                    "models": {
                        "kitti": {"checkpoint": weights, "height": 32, "width": 256},
                        "panda": {"checkpoint": "panda-run/last.pt", "profile": "pandaset"},
                    },
                }
                Path("models.yaml").write_text(yaml.safe_dump(models))
                shutil.copy("panda/001/velodyne/000000.bin", "000000.bin")
            gateway = serve(line, subs, log)
            try:
                port = int(gateway.url.rsplit(":", 1)[1])
                outputs[line] = shell(block_after(text, line).split("rangeret serve")[0], port)
                if "--models" not in line:
                    script = re.search(r"```bash\n(job=.*?)```", text, flags=re.S).group(1)
                    outputs["job"] = shell(script, port)
                assert httpx.get(gateway.url + "/healthz").status_code == 200
            finally:
                gateway.stop()
            continue
        outputs[line] = run(line, subs)

    assert set(lines) - set(ran) == set(SKIPPED)
    assert "rangeret-kitti-657" in outputs["rangeret weights list"]
    assert "\nsha256: " in outputs["rangeret weights info CHECKPOINT"]
    for seq in ("08", "42", "43"):
        assert list(Path(f"pred/sequences/{seq}/predictions").glob("*.label")), seq
    assert json.loads(Path("report.json").read_text())["miou"] >= 0
    assert Path("ablation.png").stat().st_size > 0
    assert zipfile.is_zipfile("submission.zip")
    assert Path("scan.ply").stat().st_size > 0 and Path("scan.png").stat().st_size > 0
    assert len(list(Path("simulated").rglob("*.bin"))) == 75
    assert (
        json.loads(Path("adapted/adapt.json").read_text())["target_profile"]["name"] == "my-sensor"
    )
    assert Path("run/last.pt").is_file() and Path("run-config/last.pt").is_file()
    assert Path("panda-run/last.pt").is_file()
    assert Path("000000.label").stat().st_size == 4 * len(read_scan(KITTI_SCAN))
    served, by_name = (outputs[line] for line in ran if line.startswith("rangeret serve"))
    assert '"labels"' in served and '"status_url"' in served
    assert by_name and not by_name.lstrip().startswith("{")
    assert Path("scan.label").stat().st_size > 0
    assert outputs["job"].splitlines()[0] == "succeeded" and zipfile.is_zipfile("predictions.zip")
    assert Path("kitti-657.onnx").stat().st_size > 0
    assert list(Path("pred-onnx/sequences/08/predictions").glob("*.label"))
