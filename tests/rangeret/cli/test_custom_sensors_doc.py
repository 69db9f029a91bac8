"""Every `rangeret` command of docs/custom-sensors.md, read from the page and run as written, in
order, on small simulated trees: the page's profile (its YAML example over `profile show
semantickitti`), its simulated tree, statistics, training, adapting a SemanticKITTI tree,
fine-tuning, the before/after scores and the last section's predict and evaluate.

Only the page's placeholders are replaced (ROOT and MINE: the simulated tree of the profile;
KITTI: a simulated SemanticKITTI tree; DIR, PRED: folders; MAP.yaml: SemanticKITTI's raw ids as
themselves; `rangeret-kitti-657`: a SemanticKITTI network of this resolution trained here, since
the hub is not reached), and options that keep the runs small are added (one step of a one-block
network, no loader workers, the CPU). `ray job submit` needs a cluster and is not run here."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
import yaml

from rangeret.cli.main import main
from rangeret.dataset.profiles import load_profile
from rangeret.sim import SensorConfig, simulate_dataset
from tests.support.doc_commands import ONE_STEP, SMALL_NET, code_commands, run_rangeret
from tests.support.paths import REPO

pytestmark = pytest.mark.slow

PAGE = REPO / "docs" / "custom-sensors.md"


def page_profile(text: str, shown: str) -> dict:
    """The page's example profile: its YAML block's fields over `profile show semantickitti`'s
    output, whose labels it keeps (the block abbreviates them)."""
    block = re.search(r"## The fields\n\n```yaml\n(.*?)```", text, flags=re.S).group(1)
    example = yaml.safe_load(block)
    profile = yaml.safe_load(shown)
    profile.update({k: v for k, v in example.items() if k != "labels"})
    return profile


def run(command: str, substitutions: dict[str, str]) -> str:
    """One page command in a `rangeret` process of its own, placeholders replaced, small-run
    options added; its standard output (written to the file a `>` names)."""
    words = [substitutions.get(w, w) for w in shlex.split(command)][1:]
    if ">" in words:
        cut = words.index(">")
        words, redirect = words[:cut], words[cut:]
    else:
        redirect = []
    if words[0] == "train":
        words += ONE_STEP + ([] if "--init-from" in words else SMALL_NET)
    elif words[0] in ("predict", "adapt", "simulate"):
        words.insert(1, "-q")
    return run_rangeret([*words, *redirect], command)


def test_every_command_of_the_custom_sensors_page_runs_as_written(tmp_path, monkeypatch):
    text = PAGE.read_text()
    commands = code_commands(text)
    monkeypatch.chdir(tmp_path)
    kitti = load_profile("semantickitti")
    small = SensorConfig(beams=32, azimuth_steps=512)
    trains = {seq: 1 for seq in kitti.splits["train"]}
    simulate_dataset(tmp_path / "kitti", trains, sensor=small, seed=5, profile=kitti)
    parent = tmp_path / "parent"
    argv = ["train", "-q", "--dataset", "kitti", "--train-sequences", "00", "--val-sequences"]
    argv += ["--model", "rangeret-cir", "--height", "32", "--width", "512", "--out", str(parent)]
    argv += [*SMALL_NET, *ONE_STEP]
    assert main(argv) == 0
    identity = {raw: raw for raw in kitti.labels.class_raw_ids}
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(identity))
    substitutions = {
        "ROOT": "sim",
        "MINE": "sim",
        "KITTI": "kitti",
        "DIR": "runs/train",
        "DIR/best.pt": "runs/train/best.pt",
        "PRED": "pred",
        "MAP.yaml": "map.yaml",
        "rangeret-kitti-657": str(parent / "last.pt"),
    }

    ran = []
    for command in commands:
        printed = run(command, substitutions)
        ran.append(command.split()[1])
        if command == "rangeret profile show semantickitti > my-sensor.yaml":
            profile = page_profile(text, Path("my-sensor.yaml").read_text())
            Path("my-sensor.yaml").write_text(yaml.safe_dump(profile, sort_keys=False))
        elif command.startswith("rangeret compare"):
            header = printed.splitlines()[1].split()
            assert header[:2] == ["before", "after"] and "\nmIoU " in printed
    # The page's inline steps: the profile read back as saved, and the statistics it quotes.
    shown = run("rangeret profile show my-sensor.yaml", {})
    assert yaml.safe_load(shown) == yaml.safe_load(Path("my-sensor.yaml").read_text())
    stats = "rangeret profile stats --dataset sim --profile my-sensor.yaml --sequences 0 1"
    assert run(f"{stats} --max-scans 3", {}).startswith("3 scans, ")
    assert ran.count("train") == 2 and ran.count("predict") == 3 and "adapt" in ran
    assert {"profile", "simulate", "evaluate", "compare"} <= set(ran)
    for report in ("before.json", "after.json", "report.json"):
        assert json.loads(Path(report).read_text())["profile"] == "my-sensor", report
    adapted = json.loads(Path("kitti-as-my-sensor/adapt.json").read_text())
    assert adapted["target_profile"]["name"] == "my-sensor" and len(adapted["sequences"]) == 10
