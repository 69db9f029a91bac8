"""Bounds on uploaded archives: every entry (folders too) counts against the member limit while
the archive is listed, and the extracted total is bounded by declared and by read sizes.

The unit tests drive `extract_archive`; the last ones upload to a real gateway process.
"""

from __future__ import annotations

import io
import struct
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from rangeret.dataset.layout import KITTI_LAYOUT
from rangeret.io.scans import KITTI_RECORD
from service.archives import extraction as archives
from service.archives.extraction import (
    ArchiveError,
    ArchiveLimits,
    ArchiveTooLarge,
    extract_archive,
)
from service.routes.job_errors import job_error_answer
from tests.support.gateway import Gateway, assert_error, gateway_env, start_gateway, wait_job
from tests.support.workers import build_tree, small_weights

SCAN = np.arange(40, dtype=np.float32).reshape(10, 4).tobytes()
BIN = "sequences/08/velodyne/000000.bin"
LABEL = "sequences/08/labels/000000.label"
EOCD = struct.Struct("<4s4H2LH")


def _limits(members: int = 20, extracted: int = 1 << 20, points: int = 1000) -> ArchiveLimits:
    return ArchiveLimits(
        max_bytes=64 << 20, max_members=members, max_points=points, max_extracted_bytes=extracted
    )


def _zip_bytes(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _folders(count: int) -> dict[str, bytes]:
    """`count` distinct folder entries of the layout (sequences/NNNNNN/), and one scan."""
    return {**{f"sequences/{i:06d}/": b"" for i in range(count)}, BIN: SCAN}


def _tar_gz(names: Iterator[tuple[str, bytes | None]], pax: dict[str, str] | None = None) -> bytes:
    """A .tar.gz of (name, data) members; data None makes a folder."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", format=tarfile.PAX_FORMAT) as tf:
        for name, data in names:
            info = tarfile.TarInfo(name)
            if data is None:
                info.type = tarfile.DIRTYPE
            else:
                info.size = len(data)
            if pax:
                info.pax_headers = pax
            tf.addfile(info, io.BytesIO(data) if data else None)
    return buf.getvalue()


def _write(tmp_path: Path, data: bytes, name: str = "upload") -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def _declare_entries(data: bytes, count: int) -> bytes:
    """The zip with its end record declaring `count` entries."""
    at = data.rfind(b"PK\x05\x06")
    return data[: at + 8] + struct.pack("<HH", count, count) + data[at + 12 :]


def _as_zip64(data: bytes, declared: int | None = None) -> bytes:
    """The zip with a zip64 end record and locator, and a classic end record of 0xFFFF.. fields."""
    at = data.rfind(b"PK\x05\x06")
    *_, total, size, offset, _ = EOCD.unpack_from(data, at)
    count = total if declared is None else declared
    record = struct.pack("<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, count, count, size, offset)
    locator = struct.pack("<4sLQL", b"PK\x06\x07", 0, at, 1)
    end = EOCD.pack(b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    return data[:at] + record + locator + end


def _forbid_zipfile(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if the archive is opened with zipfile (its whole listing in memory)."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("zipfile.ZipFile was opened before the entries were counted")

    monkeypatch.setattr(archives.zipfile, "ZipFile", refuse)


# Member count ------------------------------------------------------------------------------------


def test_zip_of_folders_over_the_member_limit_is_refused_before_extraction(tmp_path, monkeypatch):
    archive = _write(tmp_path, _zip_bytes({f"sequences/{i:06d}/": b"" for i in range(30)}))
    _forbid_zipfile(monkeypatch)
    with pytest.raises(ArchiveTooLarge, match="declares 30 members, more than the limit of 20"):
        extract_archive(
            archive,
            tmp_path / "data",
            _limits(members=20),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    assert not (tmp_path / "data").exists()


def test_zip_whose_end_record_understates_its_entries_is_refused_by_the_count(
    tmp_path, monkeypatch
):
    archive = _write(tmp_path, _declare_entries(_zip_bytes(_folders(30)), 10))
    _forbid_zipfile(monkeypatch)
    with pytest.raises(ArchiveTooLarge, match="more than the limit of 20 members"):
        extract_archive(
            archive,
            tmp_path / "data",
            _limits(members=20),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    assert not (tmp_path / "data").exists()


def test_zip_whose_end_record_declares_too_many_entries_is_refused_at_once(tmp_path, monkeypatch):
    archive = _write(tmp_path, _declare_entries(_zip_bytes({BIN: SCAN}), 60_000))
    zip64 = _write(tmp_path, _as_zip64(_zip_bytes({BIN: SCAN}), declared=10**12), "zip64")
    _forbid_zipfile(monkeypatch)
    with pytest.raises(ArchiveTooLarge, match="declares 60,000 members"):
        extract_archive(
            archive,
            tmp_path / "data",
            _limits(members=20),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    with pytest.raises(ArchiveTooLarge, match="declares 1,000,000,000,000 members"):
        extract_archive(
            zip64, tmp_path / "data", _limits(members=20), record=KITTI_RECORD, layout=KITTI_LAYOUT
        )


def test_damaged_central_directory_is_an_archive_error(tmp_path, monkeypatch):
    data = _zip_bytes({BIN: SCAN, LABEL: b"\0" * 40})
    start, at = data.find(b"PK\x01\x02"), data.rfind(b"PK\x05\x06")
    damaged = {
        "bad magic": data[:start] + b"XX\x01\x02" + data[start + 4 :],
        "too long": data[: at + 12] + struct.pack("<L", len(data) * 2) + data[at + 16 :],
        "no zip64": data[:at]
        + EOCD.pack(b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0),
    }
    paths = {what: _write(tmp_path, bad, what.replace(" ", "-")) for what, bad in damaged.items()}
    _forbid_zipfile(monkeypatch)
    for what, path in paths.items():
        with pytest.raises(ArchiveError, match=r"central directory|zip64") as info:
            extract_archive(
                path, tmp_path / "data", _limits(), record=KITTI_RECORD, layout=KITTI_LAYOUT
            )
        assert job_error_answer(info.value).status_code == 400, what
    assert not (tmp_path / "data").exists()


def test_tar_gz_of_many_folders_is_refused_while_listing(tmp_path, monkeypatch):
    archive = _write(
        tmp_path, _tar_gz((f"sequences/{i:06d}/", None) for i in range(5000)), "upload.tgz"
    )
    headers = 0
    real_next = tarfile.TarFile.next

    def counting_next(self: tarfile.TarFile) -> tarfile.TarInfo | None:
        nonlocal headers
        headers += 1
        return real_next(self)

    monkeypatch.setattr(tarfile.TarFile, "next", counting_next)
    with pytest.raises(ArchiveTooLarge, match="more than the limit of 20 members"):
        extract_archive(
            archive,
            tmp_path / "data",
            _limits(members=20),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    assert headers <= 22, f"{headers} tar entries were read for a limit of 20"
    assert not (tmp_path / "data").exists()


def test_tar_extended_headers_are_bounded(tmp_path):
    big = _tar_gz(iter([(BIN, SCAN)]), pax={"comment": "x" * (100 << 10)})
    with pytest.raises(ArchiveError, match="extended header") as info:
        extract_archive(
            _write(tmp_path, big),
            tmp_path / "data",
            _limits(),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    assert job_error_answer(info.value).status_code == 400
    small = _tar_gz(iter([(BIN, SCAN)]), pax={"comment": "made by a test"})
    assert (
        extract_archive(
            _write(tmp_path, small),
            tmp_path / "ok",
            _limits(),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        ).scans
        == 1
    )


def test_overlong_member_names_are_refused_as_they_are_listed(tmp_path, monkeypatch):
    name = "./" * 600 + BIN  # a valid name once cleaned, but 1,232 characters
    long_tar = _write(tmp_path, _tar_gz(iter([(name, SCAN)])), "long.tgz")
    with pytest.raises(ArchiveError, match="longer than the 1,024 allowed"):
        extract_archive(
            long_tar, tmp_path / "data", _limits(), record=KITTI_RECORD, layout=KITTI_LAYOUT
        )
    long_zip = _write(tmp_path, _zip_bytes({name: SCAN}), "long.zip")
    _forbid_zipfile(monkeypatch)
    with pytest.raises(ArchiveError, match="longer than the 1,024 allowed"):
        extract_archive(
            long_zip, tmp_path / "data", _limits(), record=KITTI_RECORD, layout=KITTI_LAYOUT
        )
    assert not (tmp_path / "data").exists()


# Extracted bytes ---------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_declared_sizes_over_the_extracted_limit_are_refused_before_writing(tmp_path, kind):
    members = {f"sequences/08/velodyne/{i:06d}.bin": b"\0" * 16_000 for i in range(10)}
    data = _zip_bytes(members) if kind == "zip" else _tar_gz(iter(members.items()))
    assert len(data) < 20_000  # far below any upload limit: only the extracted total refuses it
    with pytest.raises(ArchiveTooLarge, match="more than 100,000 bytes") as info:
        extract_archive(
            _write(tmp_path, data),
            tmp_path / "data",
            _limits(extracted=100_000),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    assert job_error_answer(info.value).status_code == 413
    assert not (tmp_path / "data").exists()
    assert extract_archive(
        _write(tmp_path, data),
        tmp_path / "ok",
        _limits(extracted=160_000),
        record=KITTI_RECORD,
        layout=KITTI_LAYOUT,
    )


@pytest.mark.parametrize("declared", [16, 400])
def test_zip_member_whose_header_lies_about_its_size_is_refused(tmp_path, declared):
    data = bytearray(_zip_bytes({BIN: np.ones((10, 4), np.float32).tobytes()}))
    central = data.find(b"PK\x01\x02")
    assert struct.unpack_from("<L", data, 22)[0] == struct.unpack_from("<L", data, central + 24)[0]
    struct.pack_into("<L", data, 22, declared)  # the local header's uncompressed size
    struct.pack_into("<L", data, central + 24, declared)  # and the central directory's
    with pytest.raises(ArchiveError) as info:
        extract_archive(
            _write(tmp_path, bytes(data)),
            tmp_path / "data",
            _limits(),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    assert job_error_answer(info.value).status_code == 400


def test_tar_member_whose_header_lies_about_its_size_is_refused(tmp_path):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tf:
        info = tarfile.TarInfo(BIN)
        info.size = len(SCAN)
        tf.addfile(info, io.BytesIO(SCAN))
    data = bytearray(buf.getvalue())
    data[124:136] = b"%011o\0" % (1 << 20)  # declares 1 MiB, holds 160 bytes
    chksum = sum(data[:148]) + 8 * 32 + sum(data[156:512])
    data[148:156] = b"%06o\0 " % chksum
    with pytest.raises(ArchiveError) as info:
        extract_archive(
            _write(tmp_path, bytes(data)),
            tmp_path / "data",
            _limits(points=1 << 20),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )
    assert job_error_answer(info.value).status_code == 400


# Zip structure -----------------------------------------------------------------------------------


def test_zip_with_bytes_prepended_still_extracts(tmp_path):
    labels = np.full(10, 40, np.uint32).tobytes()
    data = b"#!/bin/sh\necho a self-extracting stub\nexit 0\n" * 20 + _zip_bytes(
        {BIN: SCAN, LABEL: labels}
    )
    found = extract_archive(
        _write(tmp_path, data),
        tmp_path / "data",
        _limits(),
        record=KITTI_RECORD,
        layout=KITTI_LAYOUT,
    )
    assert found.scans == 1 and found.labelled == ["08"]
    assert (tmp_path / "data" / LABEL).read_bytes() == labels
    assert (tmp_path / "data" / BIN).read_bytes() == SCAN


def test_zip64_end_records_are_read(tmp_path):
    prefix = b"\x7fELF stub" * 30
    plain = _zip_bytes({BIN: SCAN, "sequences/08/": b""})
    for name, data in {"zip64": _as_zip64(plain), "prefixed": prefix + _as_zip64(plain)}.items():
        archive = _write(tmp_path, data, f"{name}.zip")
        found = extract_archive(
            archive, tmp_path / name, _limits(), record=KITTI_RECORD, layout=KITTI_LAYOUT
        )
        assert found.scans == 1 and (tmp_path / name / BIN).read_bytes() == SCAN
    # Python writes a zip64 end record for more than 65,535 entries.
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(65_540):
            zf.writestr(zipfile.ZipInfo(f"sequences/{i:06d}/"), b"")
        with zf.open(BIN, "w", force_zip64=True) as out:
            out.write(SCAN)
    data = buf.getvalue()
    assert b"PK\x06\x06" in data[-200:]
    found = extract_archive(
        _write(tmp_path, data, "many.zip"),
        tmp_path / "many",
        _limits(70_000),
        record=KITTI_RECORD,
        layout=KITTI_LAYOUT,
    )
    assert found.scans == 1
    with pytest.raises(ArchiveTooLarge, match="declares 65,541 members"):
        extract_archive(
            _write(tmp_path, data, "many.zip"),
            tmp_path / "few",
            _limits(65_540),
            record=KITTI_RECORD,
            layout=KITTI_LAYOUT,
        )


def test_one_class_label_file_that_compresses_1000_to_1_is_accepted(tmp_path):
    points = 100_000
    scan = np.random.default_rng(0).normal(size=(points, 4)).astype(np.float32).tobytes()
    labels = np.full(points, 40, np.uint32).tobytes()
    data = _zip_bytes({BIN: scan, LABEL: labels})
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        assert zf.getinfo(LABEL).file_size > 900 * zf.getinfo(LABEL).compress_size
    limits = _limits(extracted=len(scan) + len(labels), points=points)
    found = extract_archive(
        _write(tmp_path, data), tmp_path / "data", limits, record=KITTI_RECORD, layout=KITTI_LAYOUT
    )
    assert found.labelled == ["08"] and (tmp_path / "data" / LABEL).read_bytes() == labels


# A real gateway ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bounded(tmp_path_factory) -> Iterator[tuple[Gateway, Path, bytes]]:
    """A gateway of 50 members and 1 MiB extracted per archive; its jobs folder; a real scan."""
    base = tmp_path_factory.mktemp("archives")
    weights = small_weights(base)
    data = build_tree(base / "roots" / "data", labelled=0, unlabelled=1)
    scan = next((data / "sequences" / "11" / "velodyne").glob("*.bin")).read_bytes()
    env = gateway_env(
        base / "state",
        [base / "roots"],
        RANGERET_MAX_ARCHIVE_MEMBERS="50",
        RANGERET_MAX_EXTRACTED_BYTES=str(1 << 20),
    )
    gw = start_gateway(weights, env, base / "gateway.log")
    yield gw, base / "state" / "jobs", scan
    gw.stop()


def _upload(client: httpx.Client, data: bytes, name: str) -> httpx.Response:
    return client.post(
        "/v1/jobs/uploads", files={"archive": (name, data, "application/octet-stream")}
    )


def _job_folders(jobs_dir: Path) -> set[str]:
    return {p.name for p in jobs_dir.iterdir()} if jobs_dir.exists() else set()


def test_gateway_refuses_uploads_of_many_folders_and_leaves_nothing(bounded):
    gw, jobs_dir, scan = bounded
    folders = {f"sequences/{i:06d}/": b"" for i in range(200)}
    uploads = {
        "folders.zip": _zip_bytes({**folders, "sequences/11/velodyne/000000.bin": scan}),
        "folders.tar.gz": _tar_gz(
            iter([*((n, None) for n in folders), ("sequences/11/velodyne/000000.bin", scan)])
        ),
        "understated.zip": _declare_entries(_zip_bytes(folders), 5),
    }
    with gw.client() as client:
        before = _job_folders(jobs_dir)
        for name, data in uploads.items():
            detail = assert_error(_upload(client, data, name), 413)
            assert "members" in detail and "limit of 50" in detail, (name, detail)
        assert {j["id"] for j in client.get("/v1/jobs").json()["jobs"]} <= before
    assert _job_folders(jobs_dir) == before


def test_gateway_refuses_a_small_zip_that_expands_past_the_extracted_limit(bounded):
    gw, jobs_dir, _ = bounded
    zeros = {f"sequences/11/velodyne/{i:06d}.bin": b"\0" * (600 << 10) for i in range(2)}
    data = _zip_bytes(zeros)
    assert len(data) < 10_000
    with gw.client() as client:
        before = _job_folders(jobs_dir)
        detail = assert_error(_upload(client, data, "zeros.zip"), 413)
    assert "1,048,576 bytes" in detail
    assert _job_folders(jobs_dir) == before


def test_a_form_with_another_field_than_archive_is_refused_and_leaves_nothing(bounded):
    """The form holds one field, `archive`: a small field beside it, before or after the
    archive, an archive under another name, or a form without it, is a 400, and no job is made."""
    gw, jobs_dir, scan = bounded
    data = _zip_bytes({"sequences/11/velodyne/000000.bin": scan})
    archive = ("data.zip", data, "application/zip")
    with gw.client() as client:
        before = _job_folders(jobs_dir)
        for other, fields in (
            ("note", [("archive", archive), ("note", (None, b"hello"))]),
            ("model", [("model", (None, b"default")), ("archive", archive)]),
            ("file", [("file", archive)]),
        ):
            detail = assert_error(client.post("/v1/jobs/uploads", files=fields), 400)
            assert detail == f"The form field {other!r} is unexpected: send only 'archive'."
        empty = client.post("/v1/jobs/uploads", files=[("note", (None, b""))])
        assert assert_error(empty, 400).startswith("The form has no 'archive' file field")
        assert {j["id"] for j in client.get("/v1/jobs").json()["jobs"]} <= before
    assert _job_folders(jobs_dir) == before


def test_gateway_still_accepts_a_normal_archive(bounded):
    gw, _, scan = bounded
    data = _zip_bytes(
        {"sequences/": b"", "sequences/11/": b"", "sequences/11/velodyne/000000.bin": scan}
    )
    with gw.client() as client:
        r = _upload(client, data, "data.zip")
        assert r.status_code == 202, r.text
        assert wait_job(client, r.json()["id"])["state"] == "succeeded"
