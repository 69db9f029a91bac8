"""nuScenes fixtures the tests share: a small nuscenes profile (32 x 256), simulated trees,
random 17-class networks, and archives with one fault each."""

from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path

import numpy as np
import torch

from rangeret.cli.main import main
from rangeret.dataset.layout import ScanEntry, discover
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.models import build_model
from rangeret.sim import SensorConfig
from rangeret.sim.nuscenes_tree import simulate_nuscenes

WIDTH = 256


def small_profile() -> DatasetProfile:
    """The nuscenes profile at 256 columns."""
    profile = load_profile("nuscenes")
    return dataclasses.replace(
        profile, projection=dataclasses.replace(profile.projection, width=WIDTH)
    )


def write_tree(
    root: Path, scenes: dict[str, int], labelled: bool = True, version: str = "v1.0-mini"
) -> Path:
    """A simulated tree of `version` at 256 columns (seed 6)."""
    profile = load_profile("nuscenes")
    sensor = SensorConfig.for_profile(profile, azimuth_steps=WIDTH)
    simulate_nuscenes(
        root, scenes, labelled=labelled, sensor=sensor, seed=6, profile=profile, version=version
    )
    return root


def network(seed: int = 0) -> torch.nn.Module:
    """Random weights wide enough that the argmax varies from pixel to pixel (BatchNorm
    variances kept)."""
    net = build_model("rangeret-cir", 32, WIDTH, num_classes=17, layers=1).eval()
    g = torch.Generator().manual_seed(seed)
    state = {
        k: torch.randn(v.shape, generator=g) * 0.5
        if v.is_floating_point() and not k.endswith("running_var")
        else v
        for k, v in net.state_dict().items()
    }
    net.load_state_dict(state)
    return net


def entries(tree: Path, scenes: list[str], **kwargs: object) -> list[ScanEntry]:
    """The keyframes of `scenes` as the nuscenes profile lists them."""
    return discover(tree, scenes, layout=load_profile("nuscenes").layout, **kwargs).scans


def submit(tree: Path, predictions: Path, out: Path, *extra: str) -> int:
    """`rangeret submission` of the mini_val split; its exit code."""
    args = ["submission", "-q", "--profile", "nuscenes", "--dataset", str(tree)]
    args += ["--predictions", str(predictions), "--out", str(out), "--split", "mini_val"]
    return main([*args, "--method-name", "RangeRet", *extra])


def rewrite(src: Path, dst: Path, change: dict[str, bytes | None]) -> Path:
    """A copy of a zip with some members replaced (bytes) or left out (None)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            if info.filename in change:
                if change[info.filename] is not None:
                    zout.writestr(info.filename, change[info.filename])
            else:
                zout.writestr(info, zin.read(info))
    return dst


def refusals(tree: Path, predictions: Path, tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """Archives with one fault each, and the line the validator names it with."""
    good = tmp_path / "good.zip"
    assert submit(tree, predictions, good) == 0
    entry = entries(tree, ["scene-0103"], with_labels=True)[0]
    name = f"lidarseg/mini_val/{entry.name}_lidarseg.bin"
    with zipfile.ZipFile(good) as zf:
        values = np.frombuffer(zf.read(name), np.uint8).copy()
        meta = json.loads(zf.read("mini_val/submission.json"))
    zero, seventeen = values.copy(), values.copy()
    zero[3], seventeen[5] = 0, 17
    flag = json.loads(json.dumps(meta))
    flag["meta"]["use_map"] = "no"
    cases = {
        "missing": ({name: None}, f"{name} does not exist"),
        "count": ({name: values[:-1].tobytes()}, f"{name} holds {values.size - 1} predictions"),
        "zero": ({name: zero.tobytes()}, "the first 0 at point 3"),
        "seventeen": ({name: seventeen.tobytes()}, "the first 17 at point 5"),
        "flag": (
            {"mini_val/submission.json": json.dumps(flag).encode()},
            'meta.use_map must be true or false, got "no"',
        ),
    }
    return {
        case: (rewrite(good, tmp_path / f"{case}.zip", change), line)
        for case, (change, line) in cases.items()
    }
