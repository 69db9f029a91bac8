"""A test set that holds a few scans of every sequence: `rangeret submission` and
`validate-submission` refuse it in one line naming every short sequence with its counts, not in
one near-identical line per sequence; and a dead Ray job's reason keeps its error line whole."""

from __future__ import annotations

import numpy as np

from rangeret.cli.main import main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover, prediction_path
from rangeret.io.scans import write_labels
from rangeret.submission.archives import TEST_SCAN_COUNTS, TEST_SEQUENCES
from service.jobs.jobs_api import JobsApi
from tests.support.trees import make_tree


def _short_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "official test set" in line]


def test_a_short_test_set_is_one_line_naming_each_sequence(tmp_path, capsys):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {seq: [20] for seq in TEST_SEQUENCES}, labelled=False)
    rng = np.random.default_rng(0)
    for entry in discover(data, TEST_SEQUENCES, layout=KITTI_LAYOUT).scans:
        raw = semantickitti().to_raw(rng.integers(0, 20, 20))
        write_labels(prediction_path(preds, entry.sequence, entry.name), raw)
    args = ["--dataset", str(data), "--predictions", str(preds), "--out", str(tmp_path / "s.zip")]
    assert main(["submission", "-q", *args]) == 1
    (line,) = _short_lines(capsys.readouterr().err)
    for seq, expected in TEST_SCAN_COUNTS.items():
        assert f"{seq} (1 of {expected:,})" in line
    assert main(["submission", "-q", *args, "--allow-partial"]) == 0
    capsys.readouterr()
    assert main(["validate-submission", str(tmp_path / "s.zip"), "--dataset", str(data)]) == 1
    captured = capsys.readouterr()
    (line,) = _short_lines(captured.out + captured.err)
    assert all(seq in line for seq in TEST_SEQUENCES) and "--allow-partial" in line


class _Logs:
    """A Jobs API client that answers one job log."""

    def __init__(self, text: str) -> None:
        self.text = text

    def get_job_logs(self, sid: str) -> str:
        return self.text


def test_a_dead_jobs_reason_keeps_its_error_line_whole():
    error = "rangeret.exceptions.InputError: " + "the scan x.bin is malformed; " * 30
    closing = [f"(raylet) worker {i} exited" for i in range(6)]
    api = JobsApi("http://127.0.0.1:1")
    api._client = _Logs("\n".join(["Traceback (most recent call last):", "  x", error, *closing]))
    reason = api.log_tail("sid")
    assert reason.startswith(error.strip()) and "\n" not in reason
    api._client = _Logs("starting\nworking\nkilled by signal 9\n")
    assert api.log_tail("sid") == "starting | working | killed by signal 9"
