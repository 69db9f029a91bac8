"""The example run behind `make demo`: every result it announces exists and is valid."""

from __future__ import annotations

import json
import zipfile

from rangeret.demo import run_demo
from rangeret.submission import validate_submission


def test_demo_writes_report_plots_and_a_valid_partial_archive(tmp_path, capsys):
    out = run_demo(tmp_path / "demo", progress=False)
    printed = capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert 0.2 < report["miou"] < 0.9 and report["num_scans"] == 8
    assert report["sequences"] == ["08"]
    assert (out / "plots" / "iou.png").stat().st_size > 10_000
    check = validate_submission(out / "submission.zip", out / "dataset", allow_partial=True)
    assert check.ok and check.scans == 11
    with zipfile.ZipFile(out / "submission.zip") as zf:
        assert "not a real submission" in zf.read("description.txt").decode()
    assert not (out / "dataset" / "sequences" / "11" / "labels").exists()
    for name in ("report.json", "submission.zip", "confusion.png"):
        assert name in printed
