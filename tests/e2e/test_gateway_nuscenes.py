"""A nuScenes model beside a SemanticKITTI one in `rangeret serve --models`, against a real uvicorn
process, on a simulated nuScenes tree (32 x 256 networks).

A `.pcd.bin` scan is answered with the bytes of the `_lidarseg.bin` file `rangeret predict`
writes for it (one uint8 challenge class per point); a dataset job over a split, with its
version, writes its predictions where `rangeret predict` does and zips them as nuScenes' results
folder; an uploaded nuScenes archive gives the results folder of each scene's split with the same
labels; and a version for the SemanticKITTI model, an unknown split, a version or split the tree
does not hold and an archive member outside nuScenes' layout are 400s naming the field or file.
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.profiles import load_profile
from rangeret.models import build_model
from rangeret.submission.nuscenes import validate_nuscenes_submission
from tests.support.gateway import (
    NET,
    OCTET,
    Gateway,
    assert_error,
    gateway_env,
    start_gateway,
    wait_job,
)
from tests.support.nuscenes import entries, network, write_tree
from tests.support.workers import build_tree

NUSCENES = load_profile("nuscenes")
SCENES = {"scene-0061": 1, "scene-0103": 1, "scene-0916": 1}


def _predict(out: Path, *args: str) -> Path:
    """`rangeret predict` of the nuScenes model into `out`."""
    assert (
        rangeret_main(["predict", "-q", "--profile", "nuscenes", *args, "--out", str(out), *NET])
        == 0
    )
    return out


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A simulated nuScenes tree (scene-0061 of mini_train, both mini_val scenes) and a
    SemanticKITTI one, a network of each, `rangeret predict`'s labels of mini_val and of every
    scene, and the models file (`kitti` the default)."""
    base = tmp_path_factory.mktemp("nuscenes-gateway")
    roots = base / "roots"
    tree = write_tree(roots / "nu", SCENES)
    build_tree(roots / "kitti", labelled=1, unlabelled=0)
    torch.save(network(0).state_dict(), base / "nu.pt")
    torch.manual_seed(1)
    kitti = build_model("rangeret-cir", 32, 256, num_classes=20, layers=1)
    torch.save(kitti.state_dict(), base / "kitti.pt")
    weights = ["--dataset", str(tree), "--checkpoint", str(base / "nu.pt")]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        split = _predict(base / "ref-split", *weights, "--split", "mini_val")
        every = _predict(base / "ref-every", *weights, "--sequences", *SCENES)
    finally:
        torch.set_num_threads(threads)
    models = base / "models.yaml"
    models.write_text(
        yaml.safe_dump(
            {
                "default": "kitti",
                "models": {
                    "kitti": {"checkpoint": str(base / "kitti.pt")},
                    "nu": {"checkpoint": str(base / "nu.pt"), "profile": "nuscenes"},
                },
            },
            sort_keys=False,
        )
    )
    return {
        "base": base,
        "roots": roots,
        "tree": tree,
        "split": split,
        "every": every,
        "models": models,
    }


@pytest.fixture(scope="module")
def gateway(setup: dict) -> Iterator[Gateway]:
    env = gateway_env(setup["base"] / "state", [setup["roots"]], RANGERET_MAX_ARCHIVE_MEMBERS="100")
    gw = start_gateway(None, env, setup["base"] / "gateway.log", "--models", str(setup["models"]))
    yield gw
    gw.stop()


def _lidarseg(root: Path) -> dict[str, bytes]:
    """Every `_lidarseg.bin` under `root`, by its path there."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*_lidarseg.bin")}


def _zipped(client, job_id: str) -> tuple[list[str], dict[str, bytes]]:
    """A job's predictions zip: its names in order, and its files."""
    answer = client.get(f"/v1/jobs/{job_id}/predictions")
    assert answer.status_code == 200, answer.text
    with zipfile.ZipFile(io.BytesIO(answer.content)) as zf:
        names = zf.namelist()
        return names, {n: zf.read(n) for n in names if not n.endswith("/")}


def _labels(files: dict[str, bytes]) -> dict[str, bytes]:
    return {n: data for n, data in files.items() if n.endswith("_lidarseg.bin")}


def test_a_pcd_bin_scan_is_answered_with_the_label_file_rangeret_predict_writes(setup, gateway):
    mini_val = entries(setup["tree"], ["scene-0103", "scene-0916"], split="mini_val")
    kitti_scan = next((setup["roots"] / "kitti").rglob("*.bin")).read_bytes()
    with gateway.client() as client:
        answers = [
            client.post(
                "/v1/scans", params={"model": "nu"}, content=e.scan_path.read_bytes(), headers=OCTET
            )
            for e in mini_val
        ]
        as_json = client.post(
            "/v1/scans",
            params={"model": "nu", "format": "json"},
            content=mini_val[0].scan_path.read_bytes(),
            headers=OCTET,
        )
        kitti = client.post("/v1/scans", content=kitti_scan, headers=OCTET)
        profiles = {
            m: client.get("/v1/profile", params={"model": m}).json() for m in ("nu", "kitti")
        }
    for entry, answer in zip(mini_val, answers, strict=True):
        assert answer.status_code == 200, answer.text
        assert answer.headers["x-rangeret-model"] == "nu"
        assert answer.content == entry.prediction_in(setup["split"]).read_bytes()
    expected = np.frombuffer(answers[0].content, dtype=np.uint8)
    body = as_json.json()
    assert body["model"] == "nu" and body["num_points"] == expected.size
    assert body["labels"] == expected.tolist()
    names = NUSCENES.labels.class_names
    assert body["class_counts"] == {
        names[c]: int(n) for c, n in enumerate(np.bincount(expected, minlength=17)) if n
    }
    assert kitti.status_code == 200 and kitti.headers["x-rangeret-model"] == "kitti"
    assert 4 * len(kitti.content) == len(kitti_scan)  # a .label: 4 bytes per 16-byte point
    described = {
        m: (p["point_bytes"], p["label_bytes"], p["predictions"]) for m, p in profiles.items()
    }
    assert described == {"nu": (20, 1, "class"), "kitti": (16, 4, "raw")}


def test_a_dataset_job_writes_and_zips_rangeret_predicts_labels(setup, gateway):
    request = {"dataset": "nu", "model": "nu", "split": "mini_val", "version": "v1.0-mini"}
    with gateway.client() as client:
        created = client.post("/v1/jobs", json=request)
        assert created.status_code == 202, created.text
        status = wait_job(client, created.json()["id"])
        names, files = _zipped(client, status["id"])
        zipped = client.get(f"/v1/jobs/{status['id']}/predictions").content
        report = client.get(f"/v1/jobs/{status['id']}/report")
        plot = client.get(f"/v1/jobs/{status['id']}/plots/iou.png")
    assert status["state"] == "succeeded", status
    assert (status["model"], status["version"], status["split"]) == ("nu", "v1.0-mini", "mini_val")
    assert status["sequences"] == ["scene-0103", "scene-0916"] and status["done"] == 2
    reference = _lidarseg(setup["split"])
    folder = setup["base"] / "state" / "jobs" / status["id"] / "predictions"
    assert _lidarseg(folder) == reference and len(reference) == 2
    assert _labels(files) == reference
    assert names[:3] == ["lidarseg/", "lidarseg/mini_val/", "mini_val/"]
    assert names[-2:] == ["mini_val/submission.json", "description.txt"]
    archive = setup["base"] / "job.zip"
    archive.write_bytes(zipped)
    check = validate_nuscenes_submission(archive, setup["tree"], "mini_val", profile=NUSCENES)
    assert check.problems == [] and check.scans == 2
    assert report.status_code == 200 and report.json()["profile"] == "nuscenes"
    assert set(status["metrics"]["iou"]) == set(NUSCENES.labels.class_names[1:])
    assert plot.status_code == 200 and plot.headers["content-type"] == "image/png"


def test_an_archive_upload_gives_the_results_folder_of_each_scenes_split(setup, gateway):
    tree = setup["tree"]
    upload = io.BytesIO()
    with zipfile.ZipFile(upload, "w") as zf:
        for path in sorted(tree.rglob("*")):
            name = path.relative_to(tree).as_posix()
            if path.is_file() and not name.startswith("maps/"):
                zf.write(path, name)
    files = {"archive": ("nu.zip", upload.getvalue(), "application/zip")}
    with gateway.client() as client:
        created = client.post("/v1/jobs/uploads", params={"model": "nu"}, files=files)
        assert created.status_code == 202, created.text
        status = wait_job(client, created.json()["id"])
        names, files = _zipped(client, status["id"])
    assert status["state"] == "succeeded", status
    assert (status["kind"], status["version"], status["split"]) == ("archive", "v1.0-mini", None)
    assert status["sequences"] == sorted(SCENES) and status["metrics"] is not None
    assert _labels(files) == _lidarseg(setup["every"]) and len(_labels(files)) == 3
    assert {n for n in names if not n.endswith(".bin")} == {
        "lidarseg/", "lidarseg/mini_train/", "lidarseg/mini_val/", "mini_train/", "mini_val/",
        "mini_train/submission.json", "mini_val/submission.json", "description.txt",
    }  # fmt: skip
    for split in ("mini_train", "mini_val"):
        submission = json.loads(files[f"{split}/submission.json"])
        assert submission["meta"] == {
            "use_camera": False, "use_lidar": True, "use_radar": False, "use_map": False,
            "use_external": False,
        }  # fmt: skip


def test_a_selection_the_model_or_tree_lacks_is_a_400_naming_it(setup, gateway):
    stray = io.BytesIO()
    with zipfile.ZipFile(stray, "w") as zf:
        zf.writestr("maps/map.png", b"png")
    with gateway.client() as client:
        answers = {
            "kitti version": client.post(
                "/v1/jobs", json={"dataset": "kitti", "split": "valid", "version": "v1.0-mini"}
            ),
            "split": client.post(
                "/v1/jobs", json={"dataset": "nu", "model": "nu", "split": "valid"}
            ),
            "version": client.post(
                "/v1/jobs",
                json={"dataset": "nu", "model": "nu", "split": "mini_val", "version": "v1.0-test"},
            ),
            "partial": client.post(
                "/v1/jobs", json={"dataset": "nu", "model": "nu", "split": "mini_train"}
            ),
            "archive": client.post(
                "/v1/jobs/uploads",
                params={"model": "nu"},
                files={"archive": ("nu.zip", stray.getvalue(), "application/zip")},
            ),
        }
    details = {case: assert_error(answer, 400) for case, answer in answers.items()}
    assert details["kitti version"].startswith("The field 'version' is for datasets of a version")
    assert "model kitti" in details["kitti version"]
    assert details["split"].startswith("The field 'split' is 'valid'")
    assert "did you mean val?" in details["split"]
    assert details["version"].startswith("The field 'version' is 'v1.0-test'")
    assert "holds 1 of the 8 sequences of the split 'mini_train'" in details["partial"]
    assert "'maps/map.png' is not a table" in details["archive"]
