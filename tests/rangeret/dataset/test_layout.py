"""Finding sequences, scans and labels in the SemanticKITTI layout."""

from __future__ import annotations

import pytest

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import (
    KITTI_LAYOUT,
    DatasetLayoutError,
    discover,
    labels_dir,
    list_sequences,
    resolve_sequences,
)
from tests.support.trees import make_tree


def test_discovery_sorts_and_matches_labels(tmp_path):
    make_tree(tmp_path, {"08": [3, 4, 5], "01": [2]})
    assert list_sequences(tmp_path, layout=KITTI_LAYOUT) == ["01", "08"]
    found = discover(tmp_path, ["08", "01"], with_labels=True, layout=KITTI_LAYOUT)
    assert found.problems == []
    assert [e.key for e in found.scans] == ["08/000000", "08/000001", "08/000002", "01/000000"]
    assert all(e.label_path is not None and e.label_path.stem == e.name for e in found.scans)
    assert list(found.by_sequence()) == ["08", "01"]


def test_missing_files_are_named(tmp_path):
    make_tree(tmp_path, {"08": [3, 4, 5]})
    (labels_dir(tmp_path, "08", layout=KITTI_LAYOUT) / "000001.label").unlink()
    (labels_dir(tmp_path, "08", layout=KITTI_LAYOUT) / "000009.label").write_bytes(b"")
    found = discover(tmp_path, ["08", "09"], with_labels=True, layout=KITTI_LAYOUT)
    text = "\n".join(found.problems)
    assert "000001.label is missing" in text
    assert "000009.label has no matching scan" in text
    assert "sequence 09 is missing" in text
    assert len(found.problems) == 3
    assert [e.name for e in found.scans] == ["000000", "000001", "000002"]


def test_partial_copies_may_miss_sequences(tmp_path):
    make_tree(tmp_path, {"11": [1]})
    found = discover(tmp_path, ["11", "12"], missing_ok=True, layout=KITTI_LAYOUT)
    assert found.problems == [] and found.sequences == ["11"]


def test_resolve_sequences():
    assert resolve_sequences(split="valid", labels=semantickitti(), layout=KITTI_LAYOUT) == ["08"]
    assert resolve_sequences(
        sequences=["8", "08", "3", "drive-a"], labels=semantickitti(), layout=KITTI_LAYOUT
    ) == ["03", "08", "drive-a"]
    with pytest.raises(ValueError, match="not both"):
        resolve_sequences(
            split="valid", sequences=["08"], labels=semantickitti(), layout=KITTI_LAYOUT
        )
    with pytest.raises(ValueError, match="unknown split"):
        resolve_sequences(split="nope", labels=semantickitti(), layout=KITTI_LAYOUT)


def test_missing_root_is_a_clear_error(tmp_path):
    with pytest.raises(DatasetLayoutError, match="sequences does not exist"):
        list_sequences(tmp_path, layout=KITTI_LAYOUT)
