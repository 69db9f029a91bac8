"""Atomic writes and reproducible zips, the two file helpers every writer shares."""

from __future__ import annotations

import zipfile

import pytest

from rangeret.atomic import atomic_path, atomic_write_bytes, atomic_write_text
from rangeret.zipfiles import ZIP_EPOCH, ReproducibleZip


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
