"""The reasons a failed job is stored with: OS errors as their reason and their place in the job's
folder, other errors on one line, never the server's paths nor raw errno text."""

from __future__ import annotations

import errno
from pathlib import Path

from service.jobs.reasons import failure_sentence, scrub


def test_an_os_error_is_its_reason_and_where_it_happened_in_the_job_folder(tmp_path):
    folder = tmp_path / "job"
    inside = OSError(errno.ENOSPC, "No space left on device", str(folder / "predictions" / "a"))
    assert failure_sentence(inside, folder) == "no space left on device: predictions/a"
    elsewhere = OSError(errno.EACCES, "Permission denied", "/srv/data/secret.bin")
    assert failure_sentence(elsewhere, folder) == "permission denied: secret.bin"
    assert failure_sentence(OSError(errno.EIO, "Input/output error")) == "input/output error"


def test_other_errors_are_one_line_without_the_job_folder(tmp_path):
    folder = tmp_path / "job"
    error = RuntimeError(f"cannot write\n  {folder}/report.json into {folder}")
    assert failure_sentence(error, folder) == "cannot write report.json into the job's folder"
    assert failure_sentence(KeyError(), folder) == "KeyError"
    assert len(failure_sentence(ValueError("x" * 2000))) == 500


def test_scrub_makes_the_roots_relative_and_drops_errno_text():
    text = "/data/kitti/sequences/08/velodyne/000001.bin: [Errno 2] No such file"
    assert (
        scrub(text, None, [Path("/data/kitti")]) == "sequences/08/velodyne/000001.bin: No such file"
    )
    assert scrub("[Errno 5] bad", Path("/jobs/j")) == "bad"
