"""Submission archives: the writer, the validator and each way an archive can be wrong."""

from __future__ import annotations

import os
import re
import stat
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover, prediction_path, velodyne_dir
from rangeret.io.scans import KITTI_RECORD, write_labels, write_scan
from rangeret.io.zipfiles import deflate_file
from rangeret.submission.archives import (
    TEST_SCAN_COUNTS,
    TEST_SEQUENCES,
    SubmissionError,
    validate_submission,
    write_submission,
)
from rangeret.submission.leaderboard import LeaderboardEntry, description_text
from tests.support.trees import make_tree


def official_checks(archive: Path, dataset: Path) -> None:
    """What the official validator checks: folder entries, then one file per scan of the right size."""
    assert archive.name.endswith(".zip")
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        folders = [i.filename for i in infos if i.filename.endswith("/")]
        assert "sequences/" in folders
        for seq in range(11, 22):
            assert f"sequences/{seq}/" in folders
            assert f"sequences/{seq}/predictions/" in folders
        files = {i.filename: i for i in infos if not i.filename.endswith("/")}
        for seq in range(11, 22):
            vdir = os.path.join(dataset, f"sequences/{seq}/velodyne/")
            for name in sorted(os.listdir(vdir)):
                label = f"sequences/{seq}/predictions/{os.path.splitext(name)[0]}.label"
                assert label in files, label
                assert files[label].file_size / 4 == os.path.getsize(os.path.join(vdir, name)) / 16


def _predict(dataset: Path, preds: Path, seed: int = 0) -> None:
    cfg = semantickitti()
    rng = np.random.default_rng(seed)
    for entry in discover(dataset, TEST_SEQUENCES, missing_ok=True, layout=KITTI_LAYOUT).scans:
        n = entry.scan_path.stat().st_size // 16
        write_labels(
            prediction_path(preds, entry.sequence, entry.name), cfg.to_raw(rng.integers(0, 20, n))
        )


@pytest.fixture
def small_test_set(tmp_path):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"11": [30, 40], "12": [25], "15": [10, 11, 12]}, labelled=False)
    _predict(data, preds)
    return data, preds


def test_partial_archive_passes_the_official_checks(small_test_set, tmp_path):
    data, preds = small_test_set
    # The official checker lists every test sequence folder, so give the absent ones empty folders.
    for seq in TEST_SEQUENCES:
        velodyne_dir(data, seq, layout=KITTI_LAYOUT).mkdir(parents=True, exist_ok=True)
    out = tmp_path / "sub.zip"
    check = write_submission(
        preds, data, out, allow_partial=True, description="test run", labels=semantickitti()
    )
    assert check.ok and check.scans == 6 and check.partial
    official_checks(out, data)
    with zipfile.ZipFile(out) as zf:
        names = zf.namelist()
        assert zf.read("description.txt") == b"test run\n"
        assert (
            zf.read("sequences/11/predictions/000001.label")
            == prediction_path(preds, "11", "000001").read_bytes()
        )
    assert names[0] == "sequences/" and len([n for n in names if n.endswith("/")]) == 23
    assert validate_submission(out, data, allow_partial=True, labels=semantickitti()).ok


def test_archive_is_reproducible(small_test_set, tmp_path):
    data, preds = small_test_set
    a = write_submission(
        preds, data, tmp_path / "a.zip", allow_partial=True, labels=semantickitti()
    ).path
    b = write_submission(
        preds, data, tmp_path / "b.zip", allow_partial=True, labels=semantickitti()
    ).path
    assert a.read_bytes() == b.read_bytes()


@pytest.mark.parametrize("workers", [2, 8])
def test_archive_is_the_same_for_any_number_of_workers(small_test_set, tmp_path, workers):
    data, preds = small_test_set
    one = write_submission(
        preds, data, tmp_path / "one.zip", allow_partial=True, workers=1, labels=semantickitti()
    )
    many = write_submission(
        preds,
        data,
        tmp_path / "many.zip",
        allow_partial=True,
        workers=workers,
        labels=semantickitti(),
    )
    assert many.ok and many.scans == one.scans == 6
    assert many.path.read_bytes() == one.path.read_bytes()
    with zipfile.ZipFile(many.path) as zf:
        assert zf.testzip() is None


def test_cli_workers_option(small_test_set, tmp_path):
    data, preds = small_test_set
    base = ["submission", "-q", "--predictions", str(preds), "--dataset", str(data)]
    base += ["--allow-partial"]
    assert main([*base, "--out", str(tmp_path / "a.zip"), "--workers", "2"]) == 0
    description = description_text(
        LeaderboardEntry(), written_by="rangeret submission", checkpoint_sha256=None
    )
    write_submission(
        preds,
        data,
        tmp_path / "b.zip",
        allow_partial=True,
        workers=1,
        description=description,
        labels=semantickitti(),
    )
    assert (tmp_path / "a.zip").read_bytes() == (tmp_path / "b.zip").read_bytes()
    assert main([*base, "--out", str(tmp_path / "c.zip"), "--workers", "0"]) != 0
    assert not (tmp_path / "c.zip").exists()


def test_a_failing_compression_leaves_no_archive(small_test_set, tmp_path, monkeypatch):
    data, preds = small_test_set
    out = tmp_path / "s.zip"
    out.write_bytes(b"previous")

    def deflate(name, content):
        if name.endswith("12/predictions/000000.label"):
            raise MemoryError("no memory for this one")
        return deflate_file(name, content)

    monkeypatch.setattr("rangeret.submission.archives.deflate_file", deflate)
    with pytest.raises(MemoryError):
        write_submission(preds, data, out, allow_partial=True, workers=2, labels=semantickitti())
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.glob("*.zip*")) == ["s.zip"]


def test_nothing_is_compressed_after_a_problem(small_test_set, tmp_path, monkeypatch):
    data, preds = small_test_set
    prediction_path(preds, "11", "000000").unlink()
    deflated = []

    def deflate(name, content):
        deflated.append(name)
        return deflate_file(name, content)

    monkeypatch.setattr("rangeret.submission.archives.deflate_file", deflate)
    with pytest.raises(SubmissionError, match="is missing"):
        write_submission(
            preds, data, tmp_path / "s.zip", allow_partial=True, workers=1, labels=semantickitti()
        )
    assert deflated == []


def test_without_partial_an_incomplete_test_set_is_refused(small_test_set, tmp_path):
    data, preds = small_test_set
    with pytest.raises(SubmissionError) as info:
        write_submission(preds, data, tmp_path / "s.zip", labels=semantickitti())
    text = "\n".join(info.value.problems)
    missing = [p for p in info.value.problems if "sequences are missing" in p]
    assert len(missing) == 1 and "(no sequences/<sequence>/velodyne folder): 13, 14" in missing[0]
    assert "other scan counts than the official test set in sequences 11 (2 of 921)" in text
    assert not (tmp_path / "s.zip").exists()
    assert list(tmp_path.glob("*.zip*")) == []


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (
            lambda p: prediction_path(p, "11", "000001").unlink(),
            r"11/predictions/000001\.label is missing",
        ),
        (
            lambda p: write_labels(prediction_path(p, "12", "000000"), np.full(24, 10, np.uint32)),
            "holds 24 labels but its scan has 25",
        ),
        (
            lambda p: write_labels(prediction_path(p, "15", "000002"), np.full(12, 252, np.uint32)),
            r"raw ids .* cannot produce \(e\.g\. \[252\]\)",
        ),
        (
            lambda p: write_labels(prediction_path(p, "15", "000000"), np.full(10, 1, np.uint32)),
            r"e\.g\. \[1\]",
        ),
    ],
)
def test_writer_lists_wrong_predictions_and_writes_nothing(
    small_test_set, tmp_path, damage, message
):
    data, preds = small_test_set
    damage(preds)
    with pytest.raises(SubmissionError, match=message):
        write_submission(
            preds, data, tmp_path / "s.zip", allow_partial=True, labels=semantickitti()
        )
    assert list(tmp_path.glob("*.zip*")) == []


def test_writer_lists_every_problem_at_once(small_test_set, tmp_path):
    data, preds = small_test_set
    prediction_path(preds, "11", "000000").unlink()
    prediction_path(preds, "15", "000001").unlink()
    with pytest.raises(SubmissionError) as info:
        write_submission(
            preds, data, tmp_path / "s.zip", allow_partial=True, labels=semantickitti()
        )
    assert len(info.value.problems) == 2


def _rezip(src: Path, dst: Path, drop=(), add=(), keep_dirs=True) -> Path:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            if info.filename in drop or (not keep_dirs and info.filename.endswith("/")):
                continue
            zout.writestr(info, zin.read(info))
        for item in add:
            if isinstance(item, zipfile.ZipInfo):
                zout.writestr(item, b"x")
            else:
                zout.writestr(item[0], item[1])
    return dst


def _symlink(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info


@pytest.mark.filterwarnings("ignore:Duplicate name")
@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (dict(keep_dirs=False), "directory entry 'sequences/' is missing"),
        (dict(drop=["sequences/21/predictions/"]), "'sequences/21/predictions/' is missing"),
        (
            dict(drop=["sequences/12/predictions/000000.label"]),
            r"sequences/12/predictions/000000\.label is missing",
        ),
        (dict(add=[("sequences/../evil.label", b"")]), "contains '..'"),
        (dict(add=[("/etc/passwd", b"")]), "absolute"),
        (dict(add=[_symlink("sequences/11/predictions/link.label")]), "link or special file"),
        (dict(add=[("notes/readme.md", b"hi")]), "unexpected entry 'notes/readme.md'"),
        (
            dict(
                add=[("sequences/11/predictions/000000.label", np.zeros(30, np.uint32).tobytes())]
            ),
            "appears more than once",
        ),
    ],
)
def test_validator_failures(small_test_set, tmp_path, edit, message):
    data, preds = small_test_set
    good = write_submission(
        preds, data, tmp_path / "good.zip", allow_partial=True, labels=semantickitti()
    ).path
    bad = _rezip(good, tmp_path / "bad.zip", **edit)
    check = validate_submission(bad, data, allow_partial=True, labels=semantickitti())
    assert not check.ok
    assert any(re.search(message, p) for p in check.problems), check.problems
    assert "INVALID" in check.summary()


def test_validator_refuses_non_zips_and_wrong_names(small_test_set, tmp_path):
    data, _ = small_test_set
    (tmp_path / "x.zip").write_bytes(b"not a zip")
    assert (
        "not a readable zip"
        in validate_submission(tmp_path / "x.zip", data, True, labels=semantickitti()).problems[0]
    )
    (tmp_path / "x.tar").write_bytes(b"")
    assert (
        "must end with .zip"
        in validate_submission(tmp_path / "x.tar", data, True, labels=semantickitti()).problems[0]
    )
    assert (
        "does not exist"
        in validate_submission(tmp_path / "none.zip", data, True, labels=semantickitti()).problems[
            -1
        ]
    )


def test_partial_archive_only_needs_the_scans_the_dataset_holds(small_test_set, tmp_path):
    data, preds = small_test_set
    good = write_submission(
        preds, data, tmp_path / "good.zip", allow_partial=True, labels=semantickitti()
    ).path
    (velodyne_dir(data, "15", layout=KITTI_LAYOUT) / "000002.bin").unlink()
    assert validate_submission(good, data, allow_partial=True, labels=semantickitti()).ok
    check = validate_submission(good, data, allow_partial=False, labels=semantickitti())
    assert any("15/predictions/000002.label has no matching test scan" in p for p in check.problems)


@pytest.mark.slow
def test_full_test_split_archive_without_partial(tmp_path):
    """A dataset with the official scan counts (one point per scan) gives a complete archive."""
    data, preds = tmp_path / "data", tmp_path / "pred"
    point = np.array([[5.0, 1.0, -1.0, 0.3]], np.float32)
    label = np.array([40], np.uint32)
    for seq, count in TEST_SCAN_COUNTS.items():
        for i in range(count):
            write_scan(
                velodyne_dir(data, seq, layout=KITTI_LAYOUT) / f"{i:06d}.bin",
                point,
                record=KITTI_RECORD,
            )
            write_labels(prediction_path(preds, seq, f"{i:06d}"), label)
    out = tmp_path / "full.zip"
    check = write_submission(preds, data, out, labels=semantickitti())
    assert check.ok and check.scans == 20_351 and not check.partial
    official_checks(out, data)
    (velodyne_dir(data, "19", layout=KITTI_LAYOUT) / "004980.bin").unlink()
    check = validate_submission(out, data, labels=semantickitti())
    assert any("official test set in sequence 19 (4,980 of 4,981)" in p for p in check.problems)
