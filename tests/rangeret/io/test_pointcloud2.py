"""The PointCloud2 layout in numpy: decode any field layout, append fields keeping every byte."""

from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest

from rangeret.io.pointcloud2 import (
    DATATYPES,
    FLOAT32,
    FLOAT64,
    INT8,
    UINT8,
    UINT16,
    UINT32,
    CloudMessageError,
    append_fields,
    append_labels,
    decode,
    layout_of,
    pack_rgb,
)


def message(fields, values, *, point_step=None, row_pad=0, height=1, bigendian=False):
    """A PointCloud2-like object: `fields` (name, offset, datatype, count), `values` by name."""
    order = ">" if bigendian else "<"
    n = len(next(iter(values.values())))
    step = point_step or max(o + np.dtype(DATATYPES[d]).itemsize * c for _, o, d, c in fields)
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [(order + DATATYPES[d], (c,)) if c > 1 else order + DATATYPES[d]
                        for _, _, d, c in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": step,
        }
    )  # fmt: skip
    records = np.zeros(n, dtype=dtype)
    for name, v in values.items():
        records[name] = v
    width = n // height
    rows = np.full((height, width * step + row_pad), 0xEE, dtype=np.uint8)
    rows[:, : width * step] = records.view(np.uint8).reshape(height, width * step)
    return SimpleNamespace(
        fields=[SimpleNamespace(name=a, offset=b, datatype=c, count=d) for a, b, c, d in fields],
        height=height,
        width=width,
        point_step=step,
        row_step=width * step + row_pad,
        is_bigendian=bigendian,
        data=rows.reshape(-1),
    )


XYZI = [("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1), ("z", 8, FLOAT32, 1), ("intensity", 12, FLOAT32, 1)]  # fmt: skip


def _xyzi(n=5):
    rng = np.random.default_rng(0)
    return {name: rng.normal(size=n).astype(np.float32) for name in ("x", "y", "z", "intensity")}


def test_decode_a_dense_cloud_in_point_order():
    values = _xyzi()
    layout, columns = decode(message(XYZI, values), "bag: /points 0")
    assert layout.names() == ["x", "y", "z", "intensity"] and layout.num_points == 5
    for name, v in values.items():
        np.testing.assert_array_equal(columns[name], v)
        assert columns[name].dtype == np.float32


def test_decode_with_point_padding_fields_out_of_order_and_row_padding():
    values = _xyzi(6)
    fields = [("intensity", 20, FLOAT32, 1), ("z", 12, FLOAT32, 1), ("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1)]  # fmt: skip
    msg = message(fields, values, point_step=32, row_pad=7, height=2)
    layout, columns = decode(msg, "s")
    assert (layout.height, layout.width, layout.point_step, layout.row_step) == (2, 3, 32, 103)
    for name, v in values.items():
        np.testing.assert_array_equal(columns[name], v)


@pytest.mark.parametrize("bigendian", [False, True])
def test_every_datatype_in_either_byte_order(bigendian):
    fields, values, offset = [], {}, 0
    for datatype, code in sorted(DATATYPES.items()):
        dtype = np.dtype(code)
        if dtype.kind == "f":
            v = np.array([-1.5, 0.0, np.finfo(dtype).max], dtype=dtype)
        else:
            info = np.iinfo(dtype)
            v = np.array([info.min, 1, info.max], dtype=dtype)
        fields.append((f"f{datatype}", offset, datatype, 1))
        values[f"f{datatype}"] = v
        offset += dtype.itemsize + 1  # unaligned on purpose
    _, columns = decode(message(fields, values, bigendian=bigendian), "s")
    for name, v in values.items():
        np.testing.assert_array_equal(columns[name], v)
        assert columns[name].dtype == v.dtype and columns[name].dtype.isnative


def test_a_field_of_count_above_one_is_an_n_by_count_array():
    v = np.arange(12, dtype=np.uint16).reshape(4, 3)
    msg = message([("x", 0, FLOAT32, 1), ("v", 4, UINT16, 3)], {"x": np.ones(4), "v": v})
    _, columns = decode(msg, "s")
    assert columns["v"].shape == (4, 3)
    np.testing.assert_array_equal(columns["v"], v)


def test_decode_reads_bytes_and_array_data_alike():
    values = _xyzi(3)
    msg = message(XYZI, values)
    for data in (bytes(msg.data), array.array("B", bytes(msg.data)), msg.data):
        msg.data = data
        np.testing.assert_array_equal(decode(msg, "s")[1]["x"], values["x"])


def test_an_empty_cloud_decodes_to_empty_fields():
    msg = message(XYZI, {k: v[:0] for k, v in _xyzi().items()})
    layout, columns = decode(msg, "s")
    assert layout.num_points == 0 and columns["x"].shape == (0,)


def _broken(**change):
    msg = message(XYZI, _xyzi(4))
    for key, value in change.items():
        setattr(msg, key, value)
    return msg


@pytest.mark.parametrize(
    ("msg", "kind", "words"),
    [
        (_broken(fields=[SimpleNamespace(name="x", offset=0, datatype=9, count=1)]), "datatype",
         "unknown datatype 9"),
        (_broken(fields=[SimpleNamespace(name="x", offset=0, datatype=7, count=0)]), "count",
         "count 0"),
        (_broken(fields=[SimpleNamespace(name="x", offset=0, datatype=7, count=1)] * 2),
         "duplicate", "appears twice"),
        (_broken(point_step=12), "point_step", "'intensity' (offset 12, 4 bytes) does not fit"),
        (_broken(point_step=0, fields=[]), "point_step", "point_step is 0"),
        (_broken(row_step=60), "row_step", "row_step 60 is less than width 4 x point_step 16"),
        (_broken(data=np.zeros(60, np.uint8)), "size", "holds 60 bytes of data"),
        (_broken(height=2), "size", "height 2 x row_step 64 is 128"),
    ],
)  # fmt: skip
def test_each_bad_layout_is_one_error_of_its_kind(msg, kind, words):
    with pytest.raises(CloudMessageError) as err:
        decode(msg, "run.bag: /points message 3")
    assert err.value.kind == kind
    assert str(err.value).startswith("run.bag: /points message 3: ") and words in str(err.value)


def test_append_fields_keeps_every_input_byte_and_adds_the_new_ones():
    values = _xyzi(6)
    msg = message(XYZI, values, point_step=18, row_pad=5, height=2)
    layout = layout_of(msg)
    labels = np.arange(6, dtype=np.uint32) * 1000
    conf = np.linspace(0, 1, 6, dtype=np.float32)
    fields, step, data = append_fields(
        layout, msg.data, {"label": (UINT32, labels), "confidence": (FLOAT32, conf)}
    )
    assert [f.name for f in fields] == ["x", "y", "z", "intensity", "label", "confidence"]
    assert [(f.offset, f.datatype) for f in fields[4:]] == [(20, UINT32), (24, FLOAT32)]
    assert step == 28 and len(data) == 6 * 28
    out = np.frombuffer(data, np.uint8).reshape(6, 28)
    rows = np.asarray(msg.data).reshape(2, msg.row_step)[:, : 3 * 18].reshape(6, 18)
    np.testing.assert_array_equal(out[:, :18], rows)  # the padding bytes too
    again = SimpleNamespace(
        fields=fields, height=2, width=3, point_step=step, row_step=3 * step,
        is_bigendian=False, data=data,
    )  # fmt: skip
    _, columns = decode(again, "s")
    np.testing.assert_array_equal(columns["label"], labels)
    np.testing.assert_array_equal(columns["confidence"], conf)
    np.testing.assert_array_equal(columns["x"], values["x"])


def test_append_fields_replaces_an_existing_label_field_and_keeps_byte_order():
    old = np.array([7, 7, 7], dtype=np.uint32)
    fields = [("x", 0, FLOAT64, 1), ("label", 8, UINT32, 1), ("ring", 12, UINT8, 1)]
    msg = message(fields, {"x": [1.0, 2.0, 3.0], "label": old, "ring": [1, 2, 3]}, bigendian=True)
    new = np.array([10, 40, 50], dtype=np.uint32)
    out_fields, step, data = append_fields(layout_of(msg), msg.data, {"label": (UINT32, new)})
    assert [f.name for f in out_fields] == ["x", "ring", "label"]
    again = SimpleNamespace(
        fields=out_fields, height=1, width=3, point_step=step, row_step=3 * step,
        is_bigendian=True, data=data,
    )  # fmt: skip
    _, columns = decode(again, "s")
    np.testing.assert_array_equal(columns["label"], new)
    np.testing.assert_array_equal(columns["ring"], [1, 2, 3])
    assert np.frombuffer(data, np.uint8).reshape(3, step)[0, 16:20].tobytes() == b"\0\0\0\x0a"


def test_append_fields_to_an_int8_field_aligns_the_new_ones_to_four_bytes():
    msg = message([("i", 0, INT8, 1)], {"i": [-1, 2]})
    fields, step, data = append_fields(
        layout_of(msg), msg.data, {"label": (UINT32, np.array([1, 2], np.uint32))}
    )
    assert fields[-1].offset == 4 and step == 8 and len(data) == 16


def test_pack_rgb_is_pcl_packed_float():
    rgb = np.array([[255, 0, 0], [0, 255, 0], [1, 2, 3]], dtype=np.uint8)
    packed = pack_rgb(rgb)
    assert packed.dtype == np.float32
    assert packed.view(np.uint32).tolist() == [0xFF0000, 0x00FF00, 0x010203]


def test_append_labels_puts_instance_after_confidence_and_before_rgb():
    msg = message(XYZI, _xyzi(4))
    labels = np.array([10, 40, 30, 10], dtype=np.uint32)
    conf = np.full(4, 0.5, np.float32)
    instances = np.array([1, 0, 2, 70000], dtype=np.uint32)
    rgb = pack_rgb(np.zeros((4, 3), np.uint8))
    fields, step, data = append_labels(layout_of(msg), msg.data, labels, conf, rgb, instances)
    assert [(f.name, f.offset, f.datatype) for f in fields[4:]] == [
        ("label", 16, UINT32),
        ("confidence", 20, FLOAT32),
        ("instance", 24, UINT32),
        ("rgb", 28, FLOAT32),
    ]
    again = SimpleNamespace(
        fields=fields, height=1, width=4, point_step=step, row_step=4 * step,
        is_bigendian=False, data=data,
    )  # fmt: skip
    _, columns = decode(again, "s")
    np.testing.assert_array_equal(columns["instance"], instances)
    np.testing.assert_array_equal(columns["label"], labels)
    plain, _, _ = append_labels(layout_of(msg), msg.data, labels, conf)
    assert [f.name for f in plain[4:]] == ["label", "confidence"]
