"""The options of `rangeret ros2`: topics, QoS, the report interval, the field mapping and the
network options `rangeret predict` takes. Imports neither rclpy nor torch."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from rangeret.commands import CommandError
from rangeret.options import add_field_option, add_network_options

#: `--input-qos` choices and how the log names them.
INPUT_QOS_NAMES = {
    "sensor": "sensor data QoS (best effort, keep last 5)",
    "reliable": "reliable, keep last 5",
}
#: `--output-qos` choices and how the log names them.
OUTPUT_QOS_NAMES = {
    "reliable": "reliable, keep last 1",
    "sensor": "sensor data QoS (best effort, keep last 5)",
}


@dataclass(frozen=True)
class NodeSettings:
    """What the node does besides the network: where it reads and writes, and how."""

    input_topic: str
    output_topic: str
    input_qos: str
    output_qos: str
    rgb: bool
    report_every: float
    #: `--field NAME=FIELD` options, as given (parsed against the profile's record once loaded).
    fields: tuple[str, ...] = ()


def add_node_arguments(parser: argparse.ArgumentParser) -> None:
    """Every option of `rangeret ros2`."""
    g = parser.add_argument_group("topics")
    g.add_argument(
        "--input-topic",
        default="points",
        metavar="TOPIC",
        help="sensor_msgs/PointCloud2 topic to label (default: points)",
    )
    g.add_argument(
        "--output-topic",
        default="points_labelled",
        metavar="TOPIC",
        help="where the labelled clouds are published (default: points_labelled)",
    )
    g.add_argument(
        "--input-qos",
        choices=list(INPUT_QOS_NAMES),
        default="sensor",
        help="subscription QoS: sensor data (best effort, keep last 5; default; it matches "
        "reliable and best-effort publishers) or reliable (keep last 5)",
    )
    g.add_argument(
        "--output-qos",
        choices=list(OUTPUT_QOS_NAMES),
        default="reliable",
        help="publisher QoS: reliable, keep last 1 (default; a labelled scan is megabytes, "
        "which best effort loses on the way) or sensor data (best effort, keep last 5)",
    )
    g.add_argument(
        "--rgb",
        action="store_true",
        help="also add a packed rgb field (the profile's palette colour of each label)",
    )
    g.add_argument(
        "--report-every",
        type=float,
        default=5.0,
        metavar="SECONDS",
        help="publish /diagnostics and log latency and counts this often (default: 5)",
    )
    g.add_argument(
        "--ros-args",
        nargs=argparse.REMAINDER,
        default=[],
        dest="ros_args",
        metavar="ARG",
        help="everything after it goes to ROS 2 (remappings, `-r __node:=NAME`, log levels)",
    )
    add_field_option(g)
    add_network_options(parser)


def settings_from_args(args: argparse.Namespace) -> NodeSettings:
    """The node's settings from its options; a bad one is a CommandError naming it."""
    if args.batch_size != 1:
        raise CommandError(
            f"--batch-size {args.batch_size}: the node labels one cloud at a time (the newest)"
        )
    if not args.report_every > 0:
        raise CommandError(f"--report-every must be more than 0 seconds, got {args.report_every}")
    for option, topic in (
        ("--input-topic", args.input_topic),
        ("--output-topic", args.output_topic),
    ):
        if not topic.strip():
            raise CommandError(f"{option} must name a topic")
    if args.input_topic == args.output_topic:
        raise CommandError(
            f"--input-topic and --output-topic are both {args.input_topic!r}: the node would "
            "label its own answers"
        )
    return NodeSettings(
        input_topic=args.input_topic,
        output_topic=args.output_topic,
        input_qos=args.input_qos,
        output_qos=args.output_qos,
        rgb=args.rgb,
        report_every=args.report_every,
        fields=tuple(args.field),
    )
