"""`rangeret.io.point_files` and its format modules: formats told by extension and signature,
header-only point counts, padded and odd PCD fields, PLY list properties, truncated files named
in one line, and labelled copies in every format, with panoptic segmentation's `instance` too."""

from __future__ import annotations

import io
import struct

import laspy
import numpy as np
import pytest
from pypcd4 import Encoding, PointCloud

from rangeret.io import las, pcd, ply
from rangeret.io.point_files import (
    PointFileError,
    declared_points,
    decode_point_file,
    format_of,
    labelled_bytes,
    read_point_file,
)
from rangeret.io.scans import KITTI_RECORD, ScanFormatError
from tests.support.point_files import las_bytes, pcd_bytes, ply_bytes

RNG = np.random.default_rng(3)
#: 257 points that repeat, so that LZF compresses them (pypcd4 writes incompressible data binary).
POINTS = np.concatenate([np.tile(RNG.normal(0, 10, (16, 4)), (16, 1)), np.ones((1, 4))]).astype(
    np.float32
)


def test_formats_come_from_the_extension_else_the_signature():
    def fmt(name, head, size=1000):
        return format_of(name, head, size, record=KITTI_RECORD)

    assert fmt("a.PCD", b"") == "pcd" and fmt("b.laz", b"") == "las" and fmt("c.bin", b"") == "bin"
    assert fmt("scan", b"# .PCD v0.7") == fmt("scan", b"VERSION 0.7") == "pcd"
    assert fmt("scan", b"FIELDS x y z") == "pcd"
    assert fmt("scan", b"ply\nformat") == "ply" and fmt("scan", b"LASF\x00") == "las"
    assert fmt("scan.dat", b"\x00" * 16, 1600) == "bin"
    with pytest.raises(PointFileError, match=r"scan.dat: is not a PCD, PLY or LAS/LAZ file"):
        fmt("scan.dat", b"\x00" * 16, 1601)


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_reads_exact_with_its_header_count(encoding):
    data = pcd_bytes(POINTS, encoding)
    assert declared_points(data, "pcd", record=KITTI_RECORD, source="a.pcd") == 257
    f = decode_point_file(data, "pcd", record=KITTI_RECORD, source="a.pcd")
    assert (f.format, f.encoding, f.num_points) == ("pcd", encoding, 257)
    assert np.array_equal(np.stack([f.columns[k] for k in ("x", "y", "z", "intensity")], 1), POINTS)


def test_pcd_padding_counts_and_odd_types():
    n = 50
    cloud = PointCloud.from_points(
        [POINTS[:n, 0].astype(np.float64), POINTS[:n, 1], POINTS[:n, 2], np.arange(n, dtype=np.uint8),
         np.arange(n, dtype=np.int16), np.zeros(n, np.uint8), np.ones(n, np.float32) * 2,
         np.ones(n, np.float32) * 3],
        ("x", "y", "z", "ring", "t", "_", "n", "m"),
        (np.float64, np.float32, np.float32, np.uint8, np.int16, np.uint8, np.float32, np.float32),
    )  # fmt: skip
    out = io.BytesIO()
    cloud.save(out, encoding=Encoding.BINARY)
    body = out.getvalue().split(b"DATA binary\n", 1)[1]
    text = (
        "VERSION .7\nFIELDS x y z ring t _ normal\nSIZE 8 4 4 1 2 1 4\nTYPE F F F U I U F\n"
        f"COUNT 1 1 1 1 1 1 2\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary\n"
    ).encode() + body
    f = decode_point_file(text, "pcd", record=KITTI_RECORD, source="odd.pcd")
    assert list(f.columns) == ["x", "y", "z", "ring", "t", "normal__0000", "normal__0001"]
    assert f.columns["x"].dtype == np.float64 and f.columns["ring"].dtype == np.uint8
    assert np.array_equal(f.columns["t"], np.arange(n)) and (f.columns["normal__0001"] == 3).all()
    assert f.notes == ("1 padding field(s) '_' skipped",)
    copy = labelled_bytes(f, np.arange(n), np.full(n, 0.5))
    assert b"FIELDS x y z ring t _ normal label confidence" in copy
    back = decode_point_file(copy, "pcd", record=KITTI_RECORD, source="copy.pcd")
    assert np.array_equal(back.columns["label"], np.arange(n))
    assert np.array_equal(back.columns["x"], f.columns["x"])


def test_a_compressed_pcd_is_refused_from_its_header_before_decompressing():
    data = pcd_bytes(POINTS, "binary_compressed")
    header = pcd.parse_header(data, "big.pcd")
    forged = data.replace(b"WIDTH 257", b"WIDTH 9000000").replace(b"POINTS 257", b"POINTS 9000000")
    body = forged[: header.data_offset + 40] + b"\xff" * 100  # garbage that cannot decompress
    assert declared_points(body, "pcd", record=KITTI_RECORD, source="big.pcd") == 9_000_000
    with pytest.raises(pcd.PcdFormatError, match=r"unpacks to .* bytes, 9000000 points need"):
        decode_point_file(body, "pcd", record=KITTI_RECORD, source="big.pcd")


@pytest.mark.parametrize(
    ("header", "problem"),
    [
        (
            b"VERSION 0.7\nFIELDS x y\nSIZE 4\nTYPE F F\nCOUNT 1 1\nDATA binary\n",
            "2 FIELDS but 1 SIZE",
        ),
        (b"VERSION 0.7\nFIELDS x\nSIZE 3\nTYPE F\nDATA binary\n", "TYPE F SIZE 3"),
        (b"VERSION 0.7\nFIELDS x\nSIZE 4\nTYPE F\nPOINTS 1\nDATA lzma\n", "DATA 'lzma'"),
        (b"VERSION 0.7\nFIELDS x\nSIZE 4\nTYPE F\nPOINTS 1\n", "no DATA line"),
        (b"VERSION 0.7\nFIELDS x x\nSIZE 4 4\nTYPE F F\nDATA ascii\n", "names a field twice"),
        (b"FIELDS x\nSIZE 4\nTYPE F\nWIDTH 2\nHEIGHT 2\nPOINTS 3\nDATA ascii\n", "POINTS 3 but"),
    ],
)
def test_bad_pcd_headers_are_named(header, problem):
    with pytest.raises(ScanFormatError, match=problem) as exc:
        decode_point_file(header, "pcd", record=KITTI_RECORD, source="h.pcd")
    assert str(exc.value).startswith("h.pcd: ")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_reads_every_format_and_skips_later_elements(fmt):
    data = ply_bytes(POINTS, fmt)
    assert declared_points(data, "ply", record=KITTI_RECORD, source="a.ply") == 257
    f = decode_point_file(data, "ply", record=KITTI_RECORD, source="a.ply")
    assert f.encoding == fmt
    assert np.array_equal(np.stack([f.columns[k] for k in ("x", "y", "z", "intensity")], 1), POINTS)
    copy = labelled_bytes(f, np.arange(257), np.linspace(0, 1, 257))
    assert b"property uint label\nproperty float confidence\nend_header" in copy
    back = ply.read_ply_cloud(copy, "copy.ply")
    assert back.header.format == fmt and back.header.comments == ("comment written by the tests",)
    assert np.array_equal(back.array["label"], np.arange(257))
    assert np.array_equal(back.array["confidence"], np.linspace(0, 1, 257).astype(np.float32))
    assert np.array_equal(back.array["y"], POINTS[:, 1])


def test_ply_list_property_in_vertex_and_truncation_are_named():
    data = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
    data += b"property list uchar int idx\nend_header\n1 1 0\n"
    with pytest.raises(ply.PlyFormatError, match=r"l.ply: vertex property 'idx' is a list"):
        decode_point_file(data, "ply", record=KITTI_RECORD, source="l.ply")
    short = ply_bytes(POINTS, "binary_big_endian")[:-3]
    with pytest.raises(ply.PlyFormatError, match=r"257 need 4112 .the file is truncated"):
        decode_point_file(short, "ply", record=KITTI_RECORD, source="t.ply")
    text = ply_bytes(POINTS, "ascii")
    with pytest.raises(ply.PlyFormatError, match="truncated"):
        decode_point_file(text[: len(text) // 2], "ply", record=KITTI_RECORD, source="t.ply")
    first = b"ply\nformat ascii 1.0\nelement face 1\nend_header\n"
    with pytest.raises(ply.PlyFormatError, match="the first element is 'element face 1'"):
        decode_point_file(first, "ply", record=KITTI_RECORD, source="f.ply")


@pytest.mark.parametrize("compressed", [False, True])
def test_las_and_laz_read_scaled_with_intensity_over_65535(compressed):
    data = las_bytes(np.abs(POINTS) % 1, compressed)
    assert las.read_header(data, "a").compressed is compressed
    assert declared_points(data, "las", record=KITTI_RECORD, source="a.las") == 257
    f = decode_point_file(data, "las", record=KITTI_RECORD, source="a.las")
    assert f.format == ("laz" if compressed else "las") and f.notes == (las.INTENSITY_NOTE,)
    assert np.allclose(f.columns["x"], np.abs(POINTS[:, 0]) % 1, atol=6e-5)
    assert np.allclose(f.columns["intensity"], np.abs(POINTS[:, 3]) % 1, atol=1e-5)
    assert f.columns["intensity"].max() <= 1
    copy = labelled_bytes(f, np.arange(257) * 1000, np.full(257, 0.75))
    back = decode_point_file(copy, "las", record=KITTI_RECORD, source="copy.las")
    assert back.format == f.format
    assert np.array_equal(back.columns["label"], np.arange(257) * 1000)
    assert back.columns["label"].dtype == np.uint32 and (back.columns["confidence"] == 0.75).all()
    with pytest.raises(las.LasFormatError, match=r"^t.laz: .*(truncated|cannot be decoded)"):
        decode_point_file(data[:-200], "las", record=KITTI_RECORD, source="t.laz")


def test_a_laz_header_gives_its_count_without_its_points():
    data = las_bytes(POINTS, True)
    offset = len(data) - 300
    broken = data[:offset] + b"\x00" * 300
    assert declared_points(broken, "las", record=KITTI_RECORD, source="b.laz") == 257
    with pytest.raises(las.LasFormatError, match=r"b.laz: the LAZ points cannot be decoded"):
        decode_point_file(broken, "las", record=KITTI_RECORD, source="b.laz")
    with pytest.raises(las.LasFormatError, match="no LASF signature"):
        las.read_header(b"LAS" + struct.pack("<I", 1), "x.las")


def test_bin_files_use_the_record_and_a_missing_file_is_named(tmp_path):
    path = tmp_path / "scan.bin"
    path.write_bytes(POINTS.tobytes())
    f = read_point_file(path, record=KITTI_RECORD)
    assert f.format == "bin" and list(f.columns) == ["x", "y", "z", "remission"]
    assert not f.can_write_labelled
    path.write_bytes(POINTS.tobytes()[:-2])
    with pytest.raises(ScanFormatError, match="not a multiple of 16"):
        read_point_file(path, record=KITTI_RECORD)
    with pytest.raises(FileNotFoundError):
        read_point_file(tmp_path / "none.pcd", record=KITTI_RECORD)
    with pytest.raises(PointFileError, match="no room for added fields"):
        labelled_bytes(decode_point_file(POINTS.tobytes(), "bin", record=KITTI_RECORD, source="s"),
                       np.zeros(257), np.zeros(257))  # fmt: skip


INSTANCES = (np.arange(257) % 7 * 70_000).astype(np.uint32)


@pytest.mark.parametrize(
    ("fmt", "data"),
    [
        ("pcd", lambda: pcd_bytes(POINTS, "ascii", ("x", "y", "z", "instance"))),
        ("pcd", lambda: pcd_bytes(POINTS, "binary_compressed")),
        ("ply", lambda: ply_bytes(POINTS, "ascii", ("x", "y", "z", "instance"))),
        ("ply", lambda: ply_bytes(POINTS, "binary_big_endian")),
        ("las", lambda: las_bytes(np.abs(POINTS) % 1, True)),
    ],
    ids=["pcd-ascii", "pcd-compressed", "ply-ascii", "ply-be", "laz"],
)
def test_labelled_copies_take_an_instance_field_after_label_and_confidence(fmt, data):
    f = decode_point_file(data(), fmt, record=KITTI_RECORD, source=f"a.{fmt}")
    labels = np.arange(257, dtype=np.uint32) + 65_000
    copy = labelled_bytes(f, labels, np.full(257, 0.25), INSTANCES)
    back = decode_point_file(copy, fmt, record=KITTI_RECORD, source=f"copy.{fmt}")
    assert list(back.columns)[-3:] == ["label", "confidence", "instance"]
    assert back.columns["instance"].dtype == np.uint32
    assert np.array_equal(back.columns["instance"], INSTANCES)  # an old `instance` replaced
    assert np.array_equal(back.columns["label"], labels)
    assert np.array_equal(back.columns["x"], f.columns["x"])
    plain = decode_point_file(
        labelled_bytes(f, labels, np.full(257, 0.25)), fmt, record=KITTI_RECORD, source="p"
    )
    # without instances an input's own `instance` stays, and none is added (nor left behind by
    # the copy before: a LAS file's decoded points are not changed by writing one)
    assert ("instance" in plain.columns) == ("instance" in f.columns)


def test_a_las_dimension_of_a_label_field_name_is_replaced_not_cut_to_its_type():
    """An input whose extra-bytes `label`, `confidence` or `instance` is narrower (uint8, as other
    labelling tools write) must not wrap the written values."""
    data = las_bytes(np.abs(POINTS) % 1, False)
    old = laspy.read(io.BytesIO(data))
    old.add_extra_dims(
        [laspy.ExtraBytesParams(name=n, type=np.uint8) for n in ("label", "confidence", "instance")]
    )
    for name in ("label", "confidence", "instance"):
        old[name] = np.full(257, 3, np.uint8)
    out = io.BytesIO()
    old.write(out)
    f = decode_point_file(out.getvalue(), "las", record=KITTI_RECORD, source="old.las")
    labels = np.resize(np.array([259, 252, 10, 40], np.uint32), 257)
    back = decode_point_file(
        labelled_bytes(f, labels, np.full(257, 0.75), INSTANCES),
        "las",
        record=KITTI_RECORD,
        source="copy.las",
    )
    assert np.array_equal(back.columns["label"], labels)
    assert (back.columns["confidence"] == np.float32(0.75)).all()
    assert np.array_equal(back.columns["instance"], INSTANCES)
    assert back.columns["label"].dtype == back.columns["instance"].dtype == np.uint32


def test_instances_of_another_count_are_refused():
    f = decode_point_file(ply_bytes(POINTS, "ascii"), "ply", record=KITTI_RECORD, source="a.ply")
    with pytest.raises(ValueError, match=r"a.ply: 257 labels, 257 confidences and 3 instances"):
        labelled_bytes(f, np.zeros(257), np.zeros(257), np.zeros(3))
