"""The pipeline's CPU stages and the record a batch travels in, without a Ray cluster."""

from __future__ import annotations

import pickle
import subprocess
import sys

import numpy as np
import pytest

from rangeret.dataset.distance import scan_bands
from rangeret.dataset.layout import KITTI_LAYOUT, discover, prediction_path, velodyne_dir
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.projection import ProjectionConfig
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan
from tests.support.trees import make_tree
from workers.stages import BatchRecord, read_and_project, write_results


@pytest.fixture
def entries(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [300, 400, 500]})
    (velodyne_dir(data, "08", layout=KITTI_LAYOUT) / "000001.bin").write_bytes(b"\x00" * 33)
    return discover(data, ["08"], with_labels=True, layout=KITTI_LAYOUT).scans


def test_a_batch_survives_encoding_between_stages(entries):
    record = read_and_project(
        BatchRecord(4, entries), ProjectionConfig(height=16, width=128), points=KITTI_RECORD
    )
    again = BatchRecord.decode(pickle.loads(pickle.dumps(record.encode())))
    assert again.index == 4 and again.entries == entries
    assert [s.error is None for s in again.loaded] == [True, False, True]
    assert "000001.bin" in again.loaded[1].error
    assert again.loaded[2].projection.num_points == 500
    assert again.times.scans["read"] == 3 and again.times.scans["project"] == 2
    # The bands found from the projection are those the scan file gives (`rangeret evaluate`'s).
    assert again.bands[1] is None
    for i in (0, 2):
        np.testing.assert_array_equal(again.bands[i], scan_bands(read_scan(entries[i].scan_path)))


def test_writer_names_failures_and_counts_labelled_scans(entries, tmp_path):
    record = BatchRecord(0, entries)
    truth = [read_labels(e.label_path) for e in entries]
    record.results = [(truth[0], None), (None, "unreadable"), (truth[2], None)]
    first = scan_bands(read_scan(entries[0].scan_path))
    record.bands = [first, None, np.full(500, 5, np.uint8)]
    out = tmp_path / "pred"
    profile = load_profile("semantickitti")
    done = BatchRecord.decode(write_results(record, str(out), profile).encode())
    assert done.failures == [None, "unreadable", None]
    assert done.points == 800 and done.results == []
    assert done.counts.num_scans == 2 and done.counts.report().accuracy == 1.0
    assert done.bands == [] and list(done.counts.by_sequence()) == ["08"]
    far = done.counts.by_distance()[5].matrix.sum()
    assert far == 500 + int((first == 5).sum())
    written = prediction_path(out, "08", entries[2].name)
    np.testing.assert_array_equal(read_labels(written), truth[2])
    assert not prediction_path(out, "08", entries[1].name).exists()


def test_a_row_that_is_not_a_batch_is_refused():
    with pytest.raises(TypeError, match="BatchRecord"):
        BatchRecord.decode({"record": pickle.dumps({"batch": 1})})


def test_the_cpu_stages_start_without_torch():
    code = "import sys, workers.stages; print('torch' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"


def test_readers_given_roots_refuse_a_scan_that_leads_out_of_them(entries, tmp_path):
    """The Ray job's readers (`--read-roots`) judge each scan when they read it: a link to a file
    outside the roots is that scan's failure; a link that stays inside is read."""
    outside = tmp_path / "elsewhere.bin"
    outside.write_bytes(entries[0].scan_path.read_bytes())
    inside_copy = entries[0].scan_path.with_name("inside.bin")
    inside_copy.write_bytes(entries[2].scan_path.read_bytes())
    entries[0].scan_path.unlink()
    entries[0].scan_path.symlink_to(outside)
    entries[2].scan_path.unlink()
    entries[2].scan_path.symlink_to(inside_copy)
    roots = (str(tmp_path / "data"),)
    record = read_and_project(
        BatchRecord(0, entries), ProjectionConfig(16, 128), points=KITTI_RECORD, within=roots
    )
    assert "leads outside the folders this run may read" in record.loaded[0].error
    assert record.loaded[2].error is None and record.loaded[2].projection.num_points == 500
    unchecked = read_and_project(
        BatchRecord(0, entries), ProjectionConfig(16, 128), points=KITTI_RECORD
    )
    assert unchecked.loaded[0].error is None
