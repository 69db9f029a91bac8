"""`rangeret predict --bag IN --topic T --out OUT` as users run it: the labels `predict --dataset`
gives, format conversion, one-line refusals and exit 1 when a message could not be labelled."""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path, velodyne_dir
from rangeret.io.bags import bag_format
from rangeret.io.pointcloud2 import FLOAT32, decode
from rangeret.io.scans import read_scan
from tests.support.bags import Cloud, pointcloud2, read_bag, write_bag
from tests.support.workers import small_weights


@pytest.fixture(scope="module")
def network(tmp_path_factory) -> list[str]:
    weights = small_weights(tmp_path_factory.mktemp("weights"))
    return ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]


def _cloud(points: np.ndarray) -> Cloud:
    return Cloud([(n, FLOAT32, points[:, i]) for i, n in enumerate(["x", "y", "z", "intensity"])])


def _bad(store):
    msg = pointcloud2(store, _cloud(np.ones((4, 4), np.float32)))
    return dataclasses.replace(msg, point_step=12)


def test_the_real_scan_gets_the_labels_of_predict_dataset(
    tmp_path, network, real_scan_path, capsys
):
    scan = velodyne_dir(tmp_path / "data", "08", layout=KITTI_LAYOUT) / "000000.bin"
    scan.parent.mkdir(parents=True)
    scan.write_bytes(real_scan_path.read_bytes())
    argv = ["predict", "-q", "--dataset", str(tmp_path / "data"), "--sequences", "08",
            "--out", str(tmp_path / "pred"), *network]  # fmt: skip
    assert main(argv) == 0
    tree = prediction_path(tmp_path / "pred", "08", "000000").read_bytes()

    points = read_scan(real_scan_path)
    source = write_bag(tmp_path / "drive", "rosbag2-sqlite3", [_cloud(points)])
    out = tmp_path / "drive-labelled.bag"
    argv = ["predict", "-q", "--bag", str(source), "--topic", "/points", "--out", str(out),
            "--bag-format", "ros1", *network]  # fmt: skip
    assert main(argv) == 0
    assert (
        "/points: 1 messages, 1 labelled, 0 written through unlabelled" in capsys.readouterr().out
    )
    assert bag_format(out) == "ros1"
    (cloud,) = [m[4] for m in read_bag(out) if m[0] == "/points"]
    _, columns = decode(cloud, "out")
    assert columns["label"].tobytes() == tree
    assert columns["confidence"].shape == (len(points),)
    assert np.all((columns["confidence"] > 0) & (columns["confidence"] <= 1))
    record = json.loads((tmp_path / "drive-labelled.bag.run.json").read_text())
    assert record["storage_in"] == "rosbag2-sqlite3" and record["storage_out"] == "ros1"
    assert record["points"] == len(points)


def test_an_existing_out_is_refused_in_one_line(tmp_path, network, capsys):
    source = write_bag(tmp_path / "in.bag", "ros1", [_cloud(np.ones((5, 4), np.float32))])
    (tmp_path / "out.bag").write_bytes(b"mine")
    argv = ["predict", "-q", "--bag", str(source), "--topic", "/points",
            "--out", str(tmp_path / "out.bag"), *network]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert (
        err
        == f"rangeret predict: error: {tmp_path / 'out.bag'} exists; pass --overwrite to replace it\n"
    )
    assert (tmp_path / "out.bag").read_bytes() == b"mine"
    assert main([*argv, "--overwrite"]) == 0
    assert bag_format(tmp_path / "out.bag") == "ros1"


def test_an_out_that_holds_the_input_or_was_not_written_here_is_never_replaced(
    tmp_path, network, capsys
):
    """`--overwrite` replaces a bag this command wrote, never the folder that holds its input
    (with everything beside it), a folder inside the input, or a folder of someone else's."""
    drive = tmp_path / "drive"
    drive.mkdir()
    (drive / "notes.txt").write_text("keep me")
    source = write_bag(drive / "in.bag", "ros1", [_cloud(np.ones((5, 4), np.float32))])
    source2 = write_bag(tmp_path / "in2", "rosbag2-sqlite3", [_cloud(np.ones((5, 4), np.float32))])
    other = tmp_path / "someone-else"
    other.mkdir()
    (other / "data.txt").write_text("theirs")
    cases = [
        (source, drive, "cannot replace a folder that holds the bag it is read from"),
        (source2, source2 / "inner", "cannot be written inside the bag it reads"),
        (source, other, "is a folder this command did not write"),
    ]
    for bag, out, words in cases:
        argv = ["predict", "-q", "--bag", str(bag), "--topic", "/points", "--out", str(out),
                "--bag-format", "rosbag2-sqlite3", "--overwrite", *network]  # fmt: skip
        assert main(argv) == 1, out
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
    assert (drive / "notes.txt").read_text() == "keep me" and bag_format(source) == "ros1"
    assert (other / "data.txt").read_text() == "theirs" and bag_format(source2) == "rosbag2-sqlite3"
    written = tmp_path / "labelled"
    argv = ["predict", "-q", "--bag", str(source), "--topic", "/points", "--out", str(written),
            "--bag-format", "rosbag2-sqlite3", *network]  # fmt: skip
    assert main(argv) == 0 and main([*argv, "--overwrite"]) == 0  # its own bag, replaced


def test_a_bad_message_exits_1_naming_how_many_failed(tmp_path, network, capsys):
    rng = np.random.default_rng(2)
    good = rng.uniform(-10, 10, size=(50, 4)).astype(np.float32)
    source = write_bag(tmp_path / "in", "rosbag2-mcap", [_cloud(good), _bad, _cloud(good)])
    out = tmp_path / "out"
    argv = [
        "predict",
        "-q",
        "--bag",
        str(source),
        "--topic",
        "/points",
        "--out",
        str(out),
        *network,
    ]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(
        "rangeret predict: error: 1 of 3 /points messages could not be labelled (written "
        f"through unchanged; see {tmp_path / 'out.run.json'})\n"
    )
    assert bag_format(out) == "rosbag2-mcap" and len(read_bag(out)) == len(read_bag(source))
    record = json.loads((tmp_path / "out.run.json").read_text())
    assert record["messages_failed"] == 1 and record["failed"][0]["kind"] == "point_step"


@pytest.mark.parametrize(
    ("extra", "line"),
    [
        (["--topic", "/imu"], "topic /imu holds sensor_msgs/msg/Imu, not sensor_msgs/msg/PointCloud2"),
        (["--topic", "/lidar"], "has no topic '/lidar'; its topics: /chat (std_msgs/msg/String)"),
        ([], "--bag needs --topic (the PointCloud2 topic to label)"),
        (["--topic", "/points", "--split", "valid"], "--split, --sequences, --allow-partial and --save-confidence are for --dataset"),
        (["--topic", "/points", "--allow-partial"], "--split, --sequences, --allow-partial and --save-confidence are for --dataset"),
        (["--topic", "/points", "--bag-format", "ros1"], "the name of a ros1 bag must end in .bag"),
    ],
)  # fmt: skip
def test_wrong_topics_and_options_are_one_line(tmp_path, network, capsys, extra, line):
    source = write_bag(tmp_path / "in", "rosbag2-sqlite3", [_cloud(np.ones((5, 4), np.float32))])
    argv = ["predict", "-q", "--bag", str(source), "--out", str(tmp_path / "out"), *extra, *network]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and line in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_without_the_bags_extra_it_stops_with_one_line(tmp_path, network, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags", None)
    argv = ["predict", "--bag", str(tmp_path / "in"), "--topic", "/points",
            "--out", str(tmp_path / "out"), *network]  # fmt: skip
    assert main(argv) == 1
    assert capsys.readouterr().err == (
        "rangeret predict --bag needs the bags extra: pip install 'rangeret-service[bags]'\n"
    )
