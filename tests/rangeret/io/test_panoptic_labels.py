"""The benchmarks' panoptic labels: SemanticKITTI's `instance << 16 | raw id` keeps the semantic
label in its low 16 bits, nuScenes-panoptic's `1000 x class + instance` numbers each class's
objects from 1 and refuses a thousandth object of one class rather than wrap it."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.io.panoptic_labels import (
    PANOPTIC_NPZ,
    SHIFTED,
    THOUSANDS,
    PanopticEncodingError,
    read_panoptic_npz,
)


def test_shifted_labels_keep_the_semantic_label_in_their_low_bits() -> None:
    raw = np.array([10, 10, 40, 30, 252], dtype=np.uint32)
    instances = np.array([7, 7, 0, 2, 65535], dtype=np.uint32)
    labels = SHIFTED.encode(raw, instances, np.array([1, 1, 9, 6, 1]))
    assert (labels & 0xFFFF == raw).all()
    assert (labels >> 16 == instances).all()
    assert (SHIFTED.semantic(labels) == raw).all() and (SHIFTED.instance(labels) == instances).all()
    with pytest.raises(PanopticEncodingError, match="at most 65535"):
        SHIFTED.encode(raw[:1], np.array([65536]), np.array([1]))


def test_thousands_labels_number_each_class_from_one() -> None:
    classes = np.array([4, 4, 4, 7, 7, 11, 4], dtype=np.uint32)
    instances = np.array([9, 9, 3, 5, 5, 0, 12], dtype=np.uint32)
    labels = THOUSANDS.encode(classes, instances, classes)
    assert labels.tolist() == [4002, 4002, 4001, 7001, 7001, 11000, 4003]
    assert (THOUSANDS.semantic(labels) == classes).all()
    assert THOUSANDS.instance(labels).tolist() == [2, 2, 1, 1, 1, 0, 3]


def test_a_thousandth_object_of_a_class_is_refused_not_wrapped() -> None:
    n = 1000
    classes = np.full(n + 1, 4, dtype=np.uint32)
    classes[-1] = 7
    instances = np.arange(1, n + 2, dtype=np.uint32)
    with pytest.raises(PanopticEncodingError, match="1000 objects of class 4; a nuScenes-panoptic"):
        THOUSANDS.encode(classes, instances, classes)
    kept = THOUSANDS.encode(classes[1:], instances[1:], classes[1:])
    assert THOUSANDS.instance(kept).max() == 999


def test_an_npz_file_round_trips_and_reads_back_from_bytes(tmp_path) -> None:
    path = tmp_path / "a_panoptic.npz"
    values = np.array([4001, 4001, 11000, 7002], dtype=np.uint32)
    PANOPTIC_NPZ.write(path, values)
    assert PANOPTIC_NPZ.read(path, 4).tolist() == values.tolist()
    assert PANOPTIC_NPZ.holds(path, 4) and not PANOPTIC_NPZ.holds(path, 5)
    assert PANOPTIC_NPZ.parse(path.read_bytes(), "x.npz", 4).tolist() == values.tolist()
    assert read_panoptic_npz(path).dtype == np.uint16
    first = path.read_bytes()
    PANOPTIC_NPZ.write(path, values)
    assert path.read_bytes() == first
