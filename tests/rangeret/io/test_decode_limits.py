"""What a point-cloud file may decode to: every header field bounded before any allocation, one
output buffer per decode (its peak measured with tracemalloc, which sees numpy's and Python's
allocations), and hostile headers refused in one line naming the file and the bound."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable

import numpy as np
import pytest

from rangeret.io.decode_limits import DecodeLimitError, DecodeLimits
from rangeret.io.las import LasFormatError
from rangeret.io.pcd import PcdFormatError
from rangeret.io.ply import PlyFormatError
from rangeret.io.point_files import decode_point_file, read_point_file
from rangeret.io.scans import KITTI_RECORD
from tests.support.hostile_files import (
    WIDE_POINT,
    bad_lzf_pcd,
    colliding_pcd,
    count_bomb_pcd,
    huge_laz,
    short_ascii_pcd,
    vlr_bomb_las,
    wide_compressed_pcd,
    wide_ply_header,
)
from tests.support.point_files import pcd_bytes, ply_bytes

MIB = 1 << 20


def peak_of(call: Callable[[], object]) -> tuple[object, int]:
    """What `call` returns (or raises) and the most bytes it held at once."""
    tracemalloc.start()
    try:
        try:
            result: object = call()
        except Exception as exc:  # the caller asserts what was raised
            result = exc
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def decode(data: bytes, fmt: str, source: str, limits: DecodeLimits = DecodeLimits()):  # noqa: B008
    return decode_point_file(data, fmt, record=KITTI_RECORD, source=source, limits=limits)


def test_a_count_past_the_values_bound_is_refused_before_a_field_is_built():
    data = count_bomb_pcd(20_000_000)
    assert len(data) == 164
    raised, peak = peak_of(lambda: decode(data, "pcd", "count.pcd"))
    assert isinstance(raised, DecodeLimitError)
    assert str(raised) == (
        "count.pcd: declares 20,000,000 values per point (its FIELDS with their COUNTs), over "
        "the limit of 4,096 a point may hold"
    )
    assert peak < 1 * MIB


def test_a_wide_compressed_pcd_decodes_into_one_buffer_within_the_limit():
    points = 10_000
    data = wide_compressed_pcd(points)
    decoded = points * WIDE_POINT
    assert len(data) * 50 < decoded  # LZF shrinks the padding
    limits = DecodeLimits(max_decoded_bytes=48 * MIB)
    f, peak = peak_of(lambda: decode(data, "pcd", "wide.pcd", limits))
    assert f.num_points == points and f.notes == ("4080 padding field(s) '_' skipped",)
    assert np.allclose(f.columns["z"], -1) and list(f.columns) == ["x", "y", "z", "intensity"]
    assert decoded <= peak < decoded + 2 * MIB, peak / decoded
    over = wide_compressed_pcd(12_500)
    raised, peak = peak_of(lambda: decode(over, "pcd", "wide.pcd", limits))
    assert isinstance(raised, DecodeLimitError) and peak < 1 * MIB
    assert str(raised) == (
        "wide.pcd: would decode to 51,200,000 bytes (12,500 points of 4,096 bytes), over the "
        "limit of 50,331,648 (--max-decoded-bytes)"
    )


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_binary_pcd_reads_in_place_and_ascii_into_one_array(encoding):
    points = np.random.default_rng(1).normal(0, 10, (200_000, 4)).astype(np.float32)
    data = pcd_bytes(points, encoding)
    f, peak = peak_of(lambda: decode(data, "pcd", "a.pcd"))
    assert np.array_equal(np.stack([f.columns[k] for k in ("x", "y", "z", "intensity")], 1), points)
    assert peak < (0.5 * MIB if encoding == "binary" else points.nbytes + 2 * MIB), peak


def test_ply_ascii_rows_read_into_one_array():
    points = np.random.default_rng(2).normal(0, 10, (200_000, 4)).astype(np.float32)
    data = ply_bytes(points, "ascii")
    f, peak = peak_of(lambda: decode(data, "ply", "a.ply"))
    assert np.array_equal(f.columns["intensity"], points[:, 3])
    assert peak < points.nbytes + 2 * MIB, peak


def test_fields_that_collide_once_expanded_are_one_line():
    with pytest.raises(PcdFormatError) as exc:
        decode(colliding_pcd(), "pcd", "c.pcd")
    assert str(exc.value) == (
        "c.pcd: the PCD fields 'i' and 'i__0000' both give the column 'i__0000' (a field with "
        "COUNT n gives NAME__0000 .. NAME__n-1)"
    )


@pytest.mark.parametrize("rows", [0, 1, 5])
def test_an_ascii_pcd_with_fewer_rows_than_points_is_truncated(rows):
    with pytest.raises(PcdFormatError) as exc:
        decode(short_ascii_pcd(rows, 20), "pcd", "s.pcd")
    noun = "point" if rows == 1 else "points"
    assert str(exc.value) == (
        f"s.pcd: the ascii PCD data holds {rows} {noun}, the header declares 20 (the file is "
        "truncated)"
    )


def test_an_ascii_row_of_another_width_or_value_is_named():
    text = pcd_bytes(np.ones((3, 4), np.float32), "ascii")
    with pytest.raises(PcdFormatError, match=r"row 3 holds 3 values, a point 4; the file is"):
        decode(text[:-3], "pcd", "w.pcd")
    with pytest.raises(PlyFormatError, match=r"could not convert string 'x' to float32"):
        decode(ply_bytes(np.ones((3, 4), np.float32), "ascii").replace(b"1 1 1 1\n", b"x 1 1 1\n", 1),
               "ply", "v.ply")  # fmt: skip


@pytest.mark.parametrize("overflowing", [False, True])
def test_a_bad_lzf_stream_is_a_sentence(overflowing):
    with pytest.raises(PcdFormatError) as exc:
        decode(bad_lzf_pcd(overflowing), "pcd", "z.pcd")
    assert str(exc.value) == (
        "z.pcd: the compressed PCD data does not decompress to the 1,024 bytes its size word "
        "declares (its LZF stream is corrupt)"
    )


def test_a_las_declaring_a_million_vlrs_is_refused_from_its_header():
    data = vlr_bomb_las(1_000_000)
    assert len(data) == 34_000
    raised, peak = peak_of(lambda: decode(data, "las", "v.las"))
    assert isinstance(raised, LasFormatError) and peak < 1 * MIB
    assert str(raised) == (
        "v.las: the LAS header declares 1,000,000 VLRs, but the 0 bytes between its header and "
        "its points (at 227 of 34,000) hold at most 0"
    )


@pytest.mark.parametrize(
    ("make", "fmt", "problem"),
    [
        (
            lambda: huge_laz(2**40),
            "las",
            "would decode to 32,985,348,833,280 bytes (1,099,511,627,776 points of 30 bytes)",
        ),
        (
            lambda: wide_ply_header(300_000),
            "ply",
            "would decode to 247,200,000 bytes (300,000 points of 824 bytes)",
        ),
        (
            lambda: pcd_bytes(np.ones((4, 4), np.float32), "binary").replace(b"WIDTH 4", b"WIDTH 99999999").replace(b"POINTS 4", b"POINTS 99999999"),
            "pcd",
            "would decode to 1,599,999,984 bytes (99,999,999 points of 16 bytes)",
        ),
    ],
)  # fmt: skip
def test_declared_sizes_past_the_limit_are_refused_before_decoding(make, fmt, problem):
    data = make()
    limits = DecodeLimits(max_decoded_bytes=200 * MIB)
    raised, peak = peak_of(lambda: decode(data, fmt, "big", limits))
    assert isinstance(raised, DecodeLimitError) and peak < 1 * MIB
    assert str(raised) == f"big: {problem}, over the limit of 209,715,200 (--max-decoded-bytes)"


def test_the_point_bound_comes_first_and_each_bound_names_its_setting():
    limits = DecodeLimits(
        max_decoded_bytes=MIB, max_points=50, decoded_name="D", points_name="RANGERET_MAX_POINTS"
    )
    with pytest.raises(DecodeLimitError) as exc:
        decode(huge_laz(2000), "las", "b", limits)
    assert str(exc.value) == "b: declares 2,000 points, over the limit of 50 (RANGERET_MAX_POINTS)"
    wide = pcd_bytes(np.ones((40, 4), np.float32), "binary").replace(
        b"SIZE 4 4 4 4", b"SIZE 8 8 8 8"
    )
    with pytest.raises(DecodeLimitError) as exc:  # F8 points: the file's point is the wider
        decode(wide, "pcd", "w", DecodeLimits(max_decoded_bytes=1000, decoded_name="D"))
    assert str(exc.value).endswith("(40 points of 32 bytes), over the limit of 1,000 (D)")


def test_a_file_is_read_whole_only_once_its_header_passed(tmp_path):
    path = tmp_path / "sparse.pcd"
    header = pcd_bytes(np.ones((4, 4), np.float32), "binary").split(b"DATA binary\n")[0]
    header = header.replace(b"WIDTH 4", b"WIDTH 30000000").replace(b"POINTS 4", b"POINTS 30000000")
    with open(path, "wb") as f:
        f.write(header + b"DATA binary\n")
        f.truncate(len(header) + 12 + 30_000_000 * 16)  # 480 MB, sparse on disk
    raised, peak = peak_of(lambda: read_point_file(path, record=KITTI_RECORD))
    assert isinstance(raised, DecodeLimitError) and peak < 1 * MIB
    assert str(raised).startswith(f"{path}: would decode to 480,000,000 bytes")


def test_lzf_decodes_the_same_where_liblzf_is_not_exported(monkeypatch):
    from rangeret.io import lzf_codec

    data = wide_compressed_pcd(300)
    direct = decode(data, "pcd", "w.pcd")
    monkeypatch.setattr(lzf_codec, "_liblzf", lambda: None)
    fallback = decode(data, "pcd", "w.pcd")
    for name, values in direct.columns.items():
        assert np.array_equal(values, fallback.columns[name]), name
    for overflowing in (False, True):
        with pytest.raises(PcdFormatError, match="its LZF stream is corrupt"):
            decode(bad_lzf_pcd(overflowing), "pcd", "z.pcd")
