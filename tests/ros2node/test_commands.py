"""`rangeret ros2`'s options: the entry module imports neither rclpy nor torch, and bad
settings are one-line errors naming the option."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from rangeret.cli.main import build_parser
from rangeret.commands import CommandError
from ros2node.options import settings_from_args
from tests.support.paths import REPO


def parse(*argv: str):
    return build_parser("ros2").parse_args(["ros2", *argv])


def test_the_entry_module_imports_neither_rclpy_nor_torch():
    code = (
        "import sys, ros2node.commands as c\n"
        "assert c.ROS2.name == 'ros2' and c.ROS2.extra == 'ros2'\n"
        "print(sorted(m for m in ('rclpy', 'torch', 'sensor_msgs') if m in sys.modules))\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=False
    )
    assert (run.returncode, run.stdout.strip()) == (0, "[]"), run.stderr


def test_the_defaults():
    settings = settings_from_args(parse())
    assert (settings.input_topic, settings.output_topic) == ("points", "points_labelled")
    assert (settings.input_qos, settings.output_qos) == ("sensor", "reliable")
    assert settings.rgb is False and settings.report_every == 5.0 and settings.fields == ()


def test_options_after_ros_args_go_to_ros():
    args = parse("--rgb", "--field", "remission=i", "--ros-args", "-r", "__node:=lab", "--rgb")
    assert args.ros_args == ["-r", "__node:=lab", "--rgb"]
    settings = settings_from_args(args)
    assert settings.rgb is True and settings.fields == ("remission=i",)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--report-every", "0"], "--report-every must be more than 0 seconds, got 0.0"),
        (["--output-topic", "points"], "--input-topic and --output-topic are both 'points'"),
        (["--input-topic", " "], "--input-topic must name a topic"),
        (["--batch-size", "4"], "--batch-size 4: the node labels one cloud at a time"),
    ],
)
def test_bad_settings_are_one_line_errors(argv, message):
    with pytest.raises(CommandError, match="^" + re.escape(message)):
        settings_from_args(parse(*argv))
