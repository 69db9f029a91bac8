"""What the ROS 2 node adds to the `rangeret` command: `rangeret ros2`.

Declared as an entry point in `pyproject.toml` and loaded by `rangeret.plugins` to build every
parser, so this module imports neither rclpy nor torch; without the `ros2` extra the command
stops with the one line naming it.
"""

from __future__ import annotations

import argparse

from rangeret.plugins import Subcommand


def _arguments(parser: argparse.ArgumentParser) -> None:
    from ros2node.options import add_node_arguments

    add_node_arguments(parser)


def _run(args: argparse.Namespace) -> int:
    from ros2node.runner import run_node

    return run_node(args)


ROS2 = Subcommand(
    "ros2",
    "a ROS 2 node: label a PointCloud2 topic into another",
    _arguments,
    _run,
    extra="ros2",
)
