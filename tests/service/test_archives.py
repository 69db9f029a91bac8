"""Uploaded archives on their own: members checked before anything is written, the limits, and
the layout and point record of the served profile."""

from __future__ import annotations

import io
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.layout import KITTI_LAYOUT, list_scans
from rangeret.dataset.profiles import load_profile
from rangeret.io.scans import KITTI_RECORD
from service.archives.extraction import (
    ArchiveError,
    ArchiveLimits,
    ArchiveTooLarge,
    extract_archive,
)

LIMITS = ArchiveLimits(
    max_bytes=1 << 20, max_members=20, max_points=1000, max_extracted_bytes=1 << 20
)
SCAN = np.arange(40, dtype=np.float32).reshape(10, 4).tobytes()
PANDASET = load_profile("pandaset")


def _zip(tmp_path: Path, members: dict[str, bytes]) -> Path:
    path = tmp_path / "upload"
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def test_archive_with_labels_is_extracted(tmp_path):
    labels = np.full(10, 40, dtype=np.uint32).tobytes()
    archive = _zip(
        tmp_path,
        {
            "sequences/": b"",
            "sequences/08/velodyne/000000.bin": SCAN,
            "./sequences/08/labels/000000.label": labels,
            "sequences/11/velodyne/000000.bin": SCAN,
            "sequences/11/velodyne/000001.bin": SCAN,
        },
    )
    found = extract_archive(
        archive, tmp_path / "data", LIMITS, record=KITTI_RECORD, layout=KITTI_LAYOUT
    )
    assert found.sequences == ["08", "11"] and found.labelled == ["08"] and found.scans == 3
    assert (
        tmp_path / "data" / "sequences" / "08" / "labels" / "000000.label"
    ).read_bytes() == labels
    assert len(list_scans(found.root, found.sequences, layout=KITTI_LAYOUT)) == 3


@pytest.mark.parametrize(
    ("members", "words"),
    [
        (
            {
                "sequences/08/velodyne/000000.bin": SCAN,
                "sequences/08/labels/000001.label": b"\0" * 40,
            },
            "no matching scan",
        ),
        (
            {
                "sequences/08/velodyne/000000.bin": SCAN,
                "sequences/08/labels/000000.label": b"\0" * 36,
            },
            "holds 9 labels",
        ),
        (
            {
                "sequences/08/velodyne/000000.bin": SCAN,
                "sequences/08/velodyne/000001.bin": SCAN,
                "sequences/08/labels/000000.label": b"\0" * 40,
            },
            "not for 1",
        ),
        ({"sequences\\08\\velodyne\\000000.bin": SCAN}, "escape"),
        ({"C:/sequences/08/velodyne/000000.bin": SCAN}, "escape"),
        ({"data/sequences/08/velodyne/000000.bin": SCAN}, "not a sequences"),
        ({"sequences/08/velodyne/000000.label": SCAN}, "not a sequences"),
        ({"sequences/08/other/": b""}, "folder outside"),
        ({"sequences/08/velodyne/000000.bin": SCAN[:-1]}, "multiple of 16"),
        ({}, "no scan"),
    ],
)
def test_bad_archive_members(tmp_path, members, words):
    with pytest.raises(ArchiveError, match=words):
        extract_archive(
            _zip(tmp_path, members),
            tmp_path / "data",
            LIMITS,
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )


def test_archive_limits_are_checked_before_writing(tmp_path):
    many = {f"sequences/08/velodyne/{i:06d}.bin": SCAN for i in range(21)}
    with pytest.raises(ArchiveTooLarge, match="members"):
        extract_archive(
            _zip(tmp_path, many), tmp_path / "a", LIMITS, record=KITTI_RECORD, layout=KITTI_LAYOUT
        )
    assert not (tmp_path / "a").exists()
    big = {"sequences/08/velodyne/000000.bin": b"\0" * 16 * 1001}
    with pytest.raises(ArchiveTooLarge, match="1,000 points"):
        extract_archive(
            _zip(tmp_path, big), tmp_path / "b", LIMITS, record=KITTI_RECORD, layout=KITTI_LAYOUT
        )
    total = {f"sequences/08/velodyne/{i:06d}.bin": b"\0" * 16000 for i in range(10)}
    with pytest.raises(ArchiveTooLarge, match="add up"):
        extract_archive(
            _zip(tmp_path, total),
            tmp_path / "c",
            ArchiveLimits(1 << 20, 20, 1000, 100_000),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )


def test_tar_duplicates_and_special_members_are_refused(tmp_path):
    def tar(*members: tuple[str, bytes, bytes]) -> Path:
        path = tmp_path / "upload.tar"
        with tarfile.open(path, "w") as tf:
            for name, data, kind in members:
                info = tarfile.TarInfo(name)
                info.type, info.size = kind, len(data)
                tf.addfile(info, io.BytesIO(data))
        return path

    name = "sequences/08/velodyne/000000.bin"
    with pytest.raises(ArchiveError, match="more than once"):
        extract_archive(
            tar((name, SCAN, tarfile.REGTYPE), (name, SCAN, tarfile.REGTYPE)),
            tmp_path / "d",
            LIMITS,
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    with pytest.raises(ArchiveError, match="pipe"):
        extract_archive(
            tar((name, b"", tarfile.FIFOTYPE)),
            tmp_path / "d",
            LIMITS,
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    with pytest.raises(ArchiveError, match=r"not a \.zip"):
        extract_archive(
            _write(tmp_path, b"junk" * 200),
            tmp_path / "d",
            LIMITS,
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )


def test_archive_of_another_profile_is_checked_with_its_record_and_laid_out_as_its_datasets(
    tmp_path,
):
    record, layout = PANDASET.points, PANDASET.layout
    scan5 = np.arange(50, dtype=np.float32).reshape(10, 5).tobytes()
    archive = _zip(
        tmp_path,
        {
            "sequences/001/velodyne/000000.bin": scan5,
            "sequences/001/labels/000000.label": np.full(10, 13, dtype=np.uint32).tobytes(),
        },
    )
    found = extract_archive(archive, tmp_path / "data", LIMITS, record=record, layout=layout)
    assert found.sequences == ["001"] and found.labelled == ["001"]
    assert (tmp_path / "data" / "001" / "velodyne" / "000000.bin").read_bytes() == scan5
    assert len(list_scans(found.root, found.sequences, layout=layout)) == 1
    with pytest.raises(ArchiveError, match=r"multiple of 20 \(5 float32 per point: .*laser_id"):
        extract_archive(
            _zip(tmp_path, {"sequences/001/velodyne/000000.bin": SCAN[:144]}),  # 9 x 16 bytes
            tmp_path / "four",
            LIMITS,
            record=record,
            layout=layout,
        )
    big = {"sequences/001/velodyne/000000.bin": b"\0" * 20 * 1001}
    with pytest.raises(ArchiveTooLarge, match="1,000 points"):
        extract_archive(_zip(tmp_path, big), tmp_path / "big", LIMITS, record=record, layout=layout)
    fits = {"sequences/001/velodyne/000000.bin": b"\0" * 20 * 1000}
    assert (
        extract_archive(
            _zip(tmp_path, fits), tmp_path / "fits", LIMITS, record=record, layout=KITTI_LAYOUT
        ).scans
        == 1
    )


def _write(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "junk"
    path.write_bytes(data)
    return path
