"""Atomic writes and reproducible zips, the two file helpers every writer shares."""

from __future__ import annotations

import stat
import zipfile
import zlib

import numpy as np
import pytest

from rangeret.io.atomic import atomic_path, atomic_write_bytes, atomic_write_text
from rangeret.io.zipfiles import ZIP_EPOCH, ReproducibleZip, map_ahead


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    with pytest.raises(TypeError):
        atomic_write_bytes(tmp_path / "f.label", object())  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []


def test_failed_body_keeps_the_previous_file_and_no_temporary(tmp_path):
    target = tmp_path / "out.bin"
    atomic_write_text(target, "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer failed")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]


def test_atomic_files_get_the_mode_a_plain_open_gives(tmp_path):
    import os

    from rangeret.io.atomic import _UMASK

    atomic_write_bytes(tmp_path / "a.bin", b"x")
    with open(tmp_path / "b.bin", "wb") as f:
        f.write(b"x")
    mode = stat.S_IMODE((tmp_path / "a.bin").stat().st_mode)
    assert mode == stat.S_IMODE((tmp_path / "b.bin").stat().st_mode) == 0o666 & ~_UMASK
    assert mode & stat.S_IRGRP or _UMASK & 0o040, "readable by the group unless the umask says no"
    assert os.access(tmp_path / "a.bin", os.R_OK)


def test_atomic_path_replaces_on_success_and_makes_folders(tmp_path):
    target = tmp_path / "a" / "b" / "out.txt"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp != target
        tmp.write_text("new")
        assert not target.exists()
    assert target.read_text() == "new"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.txt"]


def _archive(path, order):
    with ReproducibleZip(path) as zf:
        zf.add_directory("sequences/")
        for name in order:
            zf.add_file(f"sequences/{name}", name.encode() * 100)


def test_zip_bytes_depend_only_on_entries(tmp_path, monkeypatch):
    _archive(tmp_path / "a.zip", ["x", "y"])
    monkeypatch.setattr("time.time", lambda: 2_000_000_000.0)
    _archive(tmp_path / "b.zip", ["x", "y"])
    assert (tmp_path / "a.zip").read_bytes() == (tmp_path / "b.zip").read_bytes()
    _archive(tmp_path / "c.zip", ["y", "x"])
    assert (tmp_path / "a.zip").read_bytes() != (tmp_path / "c.zip").read_bytes()


def test_zip_entries_are_explicit_dirs_and_deflated_files(tmp_path):
    _archive(tmp_path / "a.zip", ["x"])
    with zipfile.ZipFile(tmp_path / "a.zip") as zf:
        infos = zf.infolist()
        assert [i.filename for i in infos] == ["sequences/", "sequences/x"]
        assert infos[0].is_dir() and infos[0].compress_type == zipfile.ZIP_STORED
        assert infos[1].compress_type == zipfile.ZIP_DEFLATED
        assert all(i.date_time == ZIP_EPOCH for i in infos)
        assert zf.read("sequences/x") == b"x" * 100


def test_directory_names_end_with_a_slash(tmp_path):
    with ReproducibleZip(tmp_path / "a.zip") as zf, pytest.raises(ValueError, match="'/'"):
        zf.add_directory("sequences")


def _members() -> list[tuple[str, bytes | str]]:
    """Files of varied sizes and kinds: empty, tiny, text, random, compressible, over 1 MiB."""
    rng = np.random.default_rng(7)
    labels = rng.choice(np.array([0, 10, 40, 44, 48, 50, 70], np.uint32), size=300_000)
    members: list[tuple[str, bytes | str]] = [
        ("sequences/empty.label", b""),
        ("sequences/one.label", b"\x01"),
        ("sequences/text.txt", "a description, with an accent: é\n"),
        ("sequences/ünïcode.label", b"name outside ASCII"),
        ("sequences/random.bin", rng.bytes(70_000)),
        ("sequences/big.label", labels.tobytes()),  # 1.2 MB
    ]
    for i, n in enumerate(rng.integers(0, 40_000, size=40)):
        members.append((f"sequences/{i:06d}.label", labels[:n].tobytes()))
    return members


def _writestr_archive(path, members) -> None:
    """The archive as `zipfile.writestr` writes the same entries, one after the other."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as zf:
        info = zipfile.ZipInfo("sequences/", date_time=ZIP_EPOCH)
        info.external_attr = (stat.S_IFDIR | 0o755) << 16 | 0x10
        zf.writestr(info, b"")
        for name, data in members:
            info = zipfile.ZipInfo(name, date_time=ZIP_EPOCH)
            info.external_attr = (stat.S_IFREG | 0o644) << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data, compresslevel=6)


def _parallel_archive(path, members, workers: int) -> None:
    with ReproducibleZip(path) as zf:
        zf.add_directory("sequences/")
        zf.add_files(((name, lambda data=data: data) for name, data in members), workers)


@pytest.mark.parametrize("workers", [1, 2, 8])
def test_parallel_archive_is_writestrs_byte_for_byte(tmp_path, workers):
    """Guards the one use of zipfile's internals: entries deflated ahead match `writestr`'s."""
    members = _members()
    _writestr_archive(tmp_path / "reference.zip", members)
    _parallel_archive(tmp_path / "parallel.zip", members, workers)
    assert (tmp_path / "parallel.zip").read_bytes() == (tmp_path / "reference.zip").read_bytes()
    with zipfile.ZipFile(tmp_path / "parallel.zip") as zf:
        assert zf.testzip() is None
        assert zf.namelist() == ["sequences/"] + [name for name, _ in members]
        for name, data in members:
            expected = data.encode() if isinstance(data, str) else data
            assert zf.read(name) == expected
            assert zlib.crc32(expected) == zf.getinfo(name).CRC


def test_add_file_and_add_files_give_the_same_archive(tmp_path):
    members = _members()[:8]
    with ReproducibleZip(tmp_path / "a.zip") as zf:
        zf.add_directory("sequences/")
        for name, data in members:
            zf.add_file(name, data)
    _parallel_archive(tmp_path / "b.zip", members, workers=4)
    assert (tmp_path / "a.zip").read_bytes() == (tmp_path / "b.zip").read_bytes()


def test_zip64_records_are_zipfiles_own(tmp_path, monkeypatch):
    """Members, offsets and entry counts past the ZIP64 limits (lowered here to small sizes) get
    the same ZIP64 headers and end records as `writestr`'s archive, which reads back."""
    monkeypatch.setattr(zipfile, "ZIP64_LIMIT", 50_000)
    monkeypatch.setattr(zipfile, "ZIP_FILECOUNT_LIMIT", 20)
    members = _members()
    _writestr_archive(tmp_path / "reference.zip", members)
    _parallel_archive(tmp_path / "parallel.zip", members, workers=2)
    data = (tmp_path / "parallel.zip").read_bytes()
    assert data == (tmp_path / "reference.zip").read_bytes()
    assert b"PK\x06\x06" in data and b"PK\x06\x07" in data  # ZIP64 end record and locator
    with zipfile.ZipFile(tmp_path / "parallel.zip") as zf:
        assert zf.testzip() is None
        assert zf.getinfo("sequences/big.label").extract_version == zipfile.ZIP64_VERSION
        assert zf.read("sequences/big.label") == dict(members)["sequences/big.label"]


def test_a_failing_member_leaves_no_archive(tmp_path):
    target = tmp_path / "out.zip"
    target.write_bytes(b"previous")

    def broken() -> bytes:
        raise OSError("unreadable label")

    files = [(name, lambda data=data: data) for name, data in _members()]
    files.insert(20, ("sequences/broken.label", broken))
    with (
        pytest.raises(OSError, match="unreadable"),
        atomic_path(target) as tmp,
        ReproducibleZip(tmp) as zf,
    ):
        zf.add_files(files, workers=4)
    assert target.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.zip"]


@pytest.mark.parametrize("workers", [1, 3])
def test_map_ahead_keeps_order_and_a_bounded_window(workers):
    taken = 0
    yielded = 0

    def items():
        nonlocal taken
        for i in range(50):
            taken += 1
            yield i

    for i, result in enumerate(map_ahead(lambda x: x * x, items(), workers)):
        assert result == i * i
        yielded += 1
        assert taken - yielded < 2 * workers
    assert yielded == 50


def test_map_ahead_refuses_no_workers():
    with pytest.raises(ValueError, match="at least 1"):
        map_ahead(str, [1], workers=0)
