"""`rangeret demo` end to end at a reduced size with the bundled demo weights: every result it
announces exists and is valid."""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

import pytest

from rangeret.dataset.labels import semantickitti
from rangeret.submission.archives import validate_submission
from rangeret.submission.leaderboard import LeaderboardEntry

pytestmark = pytest.mark.slow


def test_demo_end_to_end(tmp_path, capfd):
    """Also: Ray's own lines (its loggers, its core worker's C++ lines, written to the
    process's file descriptors) stay out of the output, in its session's log folder, which the
    demo names; the table names both point counts."""
    ray = pytest.importorskip("ray")
    from workers.demo import RAY_STDERR_LOG, run_demo

    entry = LeaderboardEntry("RangeRet demo", "https://example.org/paper.pdf")
    out = run_demo(
        tmp_path / "demo", valid_scans=2, test_scans=1, progress=False, leaderboard=entry
    )
    assert not ray.is_initialized()
    captured = capfd.readouterr()
    printed = captured.out
    for line in (captured.out + captured.err).splitlines():
        assert not re.search(r"core_worker|streaming_executor|worker\.py:\d+", line), line
    logs = next(
        line.split(":", 1)[1].strip()
        for line in printed.splitlines()
        if line.strip().startswith("Ray's own logs")
    )
    assert (Path(logs) / RAY_STDERR_LOG).is_file()
    assert re.search(r"2 scans, [\d,]+ points predicted, [\d,]+ of them scored", printed)
    report = json.loads((out / "report.json").read_text())
    assert report["num_scans"] == 2 and report["sequences"] == ["08"]
    assert len(report["checkpoint_sha256"]) == 64
    assert any("simulated street scenes only" in note for note in report["notes"])
    for name in ("confusion.png", "iou.png", "range-image.png"):
        png = out / "plots" / name
        assert png.read_bytes()[:4] == b"\x89PNG" and png.stat().st_size > 5_000
        assert name in printed
    check = validate_submission(
        out / "submission.zip", out / "dataset", allow_partial=True, labels=semantickitti()
    )
    assert check.ok and check.scans == 11
    with zipfile.ZipFile(out / "submission.zip") as zf:
        description = zf.read("description.txt").decode()
    assert description.splitlines()[:4] == [
        "name: RangeRet demo",
        "pdf url: https://example.org/paper.pdf",
        "code url: n/a",
        f"checkpoint sha256: {report['checkpoint_sha256']}",
    ]
    assert "not a real submission" in description and "simulated street scenes" in description
    assert check.warnings == []
    assert not (out / "dataset" / "sequences" / "11" / "labels").exists()
    assert "--checkpoint rangeret-kitti-657" in printed
    # The check the demo suggests for its own archive passes, and its summary has its spaces.
    suggested = re.search(
        r"(rangeret validate-submission \S+ --dataset \S+ --allow-partial)", printed
    )
    assert suggested is not None, printed
    from rangeret.cli.main import main as rangeret_main

    command, *rest = suggested.group(1).split()[1:]
    assert rangeret_main([command, "-q", *rest]) == 0
    assert not re.search(r"\):\S", printed), printed
    assert "cpu@" not in printed and re.search(r"on cpu \(\d model actors?: process", printed)
    run = json.loads((out / "predictions" / "run.json").read_text())
    assert run["runner"] == "rangeret demo" and run["demo_weights"] is True
    assert run["checkpoint_sha256"] == report["checkpoint_sha256"]
    assert run["sequences"] == ["08", *(str(s) for s in range(11, 22))]
    assert [r["runner"] for r in run["runs"]] == ["rangeret demo"]

    from rangeret.io.run_info import WeightsMismatchError, write_run_info

    other = tmp_path / "other"
    write_run_info(
        other / "predictions",
        {"checkpoint_sha256": "d" * 64},
        runner="rangeret predict",
        dataset=None,
        sequences=["08"],
        batch_size=1,
    )
    with pytest.raises(WeightsMismatchError, match="dddddddddddd"):
        run_demo(other, progress=False)
    assert sorted(p.name for p in other.iterdir()) == ["predictions"], "refused before simulating"


def test_demo_on_another_profile_needs_its_network(tmp_path, capsys):
    from rangeret.cli.main import main

    assert main(["demo", "-q", "--out", str(tmp_path / "d"), "--profile", "pandaset"]) == 1
    err = capsys.readouterr().err
    assert "only the semantickitti and nuscenes profiles have bundled demo weights" in err
    assert "--checkpoint" in err
    assert not (tmp_path / "d").exists()


def test_demo_on_pandaset_with_a_pandaset_network(tmp_path, capsys):
    pytest.importorskip("ray")
    import torch

    from rangeret.dataset.profiles import load_profile
    from rangeret.models import build_model
    from workers.demo import run_demo

    torch.manual_seed(0)
    torch.save(
        build_model("rangeret-cir", 64, 1024, num_classes=15, layers=1).state_dict(),
        tmp_path / "w.pt",
    )
    profile = load_profile("pandaset")
    out = run_demo(
        tmp_path / "demo",
        valid_scans=1,
        test_scans=1,
        checkpoint=tmp_path / "w.pt",
        progress=False,
        profile=profile,
    )
    report = json.loads((out / "report.json").read_text())
    assert report["profile"] == "pandaset" and report["sequences"] == ["005"]
    assert "unlabeled" not in report["iou"] and len(report["iou"]) == 14
    assert (out / "dataset" / "005" / "velodyne").is_dir() and not (out / "submission.zip").exists()
    assert len(list((out / "predictions").rglob("*.label"))) == 2
    assert (out / "plots" / "range-image.png").read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()


def test_demo_on_nuscenes_with_its_demo_weights(tmp_path, capsys):
    """Simulated v1.0-mini, predicted on Ray with the bundled nuScenes demo weights, scored as
    the devkit scores, and a whole mini_val archive written and validated."""
    pytest.importorskip("ray")
    from rangeret.dataset.profiles import load_profile
    from rangeret.submission.nuscenes import validate_nuscenes_submission
    from workers.demo import run_demo

    profile = load_profile("nuscenes")
    out = run_demo(tmp_path / "demo", valid_scans=2, progress=False, profile=profile)
    printed = capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["profile"] == "nuscenes" and report["scoring"] == "nuscenes"
    assert report["sequences"] == ["scene-0103", "scene-0916"] and report["num_scans"] == 2
    assert any("simulated street scenes only" in note for note in report["notes"])
    assert report["miou"] is not None and "freq_weighted_iou" in report
    assert (out / "dataset" / "v1.0-mini" / "lidarseg.json").is_file()
    assert len(list((out / "predictions" / "lidarseg" / "mini_val").iterdir())) == 2
    check = validate_nuscenes_submission(
        out / "submission.zip", out / "dataset", "mini_val", profile=profile
    )
    assert check.ok and check.scans == 2
    with zipfile.ZipFile(out / "submission.zip") as zf:
        meta = json.loads(zf.read("mini_val/submission.json"))
    assert (
        meta["meta"]["use_lidar"] is True
        and meta["method"]["checkpoint_sha256"] == (report["checkpoint_sha256"])
    )
    assert "submission archive (mini_val):" in printed
    assert (out / "plots" / "range-image.png").read_bytes()[:4] == b"\x89PNG"


def test_demo_panoptic_end_to_end(tmp_path, capsys):
    """`rangeret demo --panoptic`: objects through the pipeline, the panoptic benchmark's report
    printed with PQ beside mIoU, its archive validated, and the task in run.json."""
    pytest.importorskip("ray")
    import numpy as np

    from rangeret.cli.main import main as rangeret_main
    from workers.demo import run_demo

    out = run_demo(tmp_path / "demo", valid_scans=1, test_scans=1, progress=False, panoptic=True)
    printed = capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["benchmark"] == "semantickitti-panoptic" and report["num_scans"] == 1
    assert len(report["checkpoint_sha256"]) == 64
    headline = re.search(r"PQ (\d+\.\d\d) %, mIoU (\d+\.\d\d) % \(semantickitti-panoptic", printed)
    assert headline is not None, printed
    assert float(headline.group(1)) == pytest.approx(100 * report["pq_mean"], abs=0.006)
    assert float(headline.group(2)) == pytest.approx(100 * report["iou_mean"], abs=0.006)
    assert "panoptic evaluation report:" in printed and "PQ-dagger" in printed
    assert "--task panoptic" in printed
    labels = np.fromfile(
        out / "predictions" / "sequences" / "08" / "predictions" / "000000.label", "<u4"
    )
    assert (labels >> 16).any(), "the scan's objects"
    assert (out / "plots" / "range-image.png").read_bytes()[:4] == b"\x89PNG"
    assert not (out / "plots" / "iou.png").exists()
    validate = ["validate-submission", "-q", str(out / "submission.zip")]
    validate += ["--dataset", str(out / "dataset"), "--allow-partial", "--task", "panoptic"]
    assert rangeret_main(validate) == 0
    run = json.loads((out / "predictions" / "run.json").read_text())
    assert run["runner"] == "rangeret demo" and run["panoptic"]["min_points"] == 10


def test_demo_panoptic_needs_thing_classes(tmp_path, capsys):
    """`rangeret demo --panoptic` on a profile without thing classes: one line, nothing
    written."""
    import torch

    from rangeret.cli.main import main
    from rangeret.models import build_model

    torch.manual_seed(0)
    torch.save(
        build_model("rangeret-cir", 64, 128, num_classes=15, layers=1).state_dict(),
        tmp_path / "w.pt",
    )
    args = ["demo", "-q", "--out", str(tmp_path / "d"), "--panoptic", "--profile", "pandaset"]
    assert main([*args, "--checkpoint", str(tmp_path / "w.pt")]) == 1
    assert "the pandaset profile names no thing classes" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
