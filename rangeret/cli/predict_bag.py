"""`rangeret predict --bag IN --topic T --out OUT`: a copy of a bag whose PointCloud2 messages on
one topic carry `label` and `confidence` fields, and with --panoptic `instance` (see
`rangeret.inference.bag_runner`)."""

from __future__ import annotations

import argparse

from rangeret.cli.shared import predictor_from_args
from rangeret.commands import CommandError
from rangeret.extras import require_extra
from rangeret.io.point_fields import parse_field_overrides

#: The bag kinds `--bag-format` names (`rangeret.io.bags.BAG_FORMATS`, repeated here so the
#: parser is built without the bags extra).
BAG_FORMATS = ("rosbag2-sqlite3", "rosbag2-mcap", "ros1")


def add_bag_options(p: argparse.ArgumentParser) -> None:
    """--topic and --bag-format, the options of `--bag` (which joins the source group of
    `rangeret predict`; --overwrite, shared with the other sources, replaces an existing OUT)."""
    g = p.add_argument_group("bags (with --bag)")
    g.add_argument("--topic", metavar="T", help="the sensor_msgs/PointCloud2 topic to label")
    g.add_argument(
        "--bag-format",
        choices=list(BAG_FORMATS),
        help="the kind of bag to write (default: the input's)",
    )


def run_bag(args: argparse.Namespace) -> int:
    """Label the bag's topic into a new bag; exit 1 when a message could not be labelled."""
    require_extra("rangeret predict --bag", "bags")
    from rangeret.inference.bag_runner import label_bag
    from rangeret.io.bags import bag_format, check_target, open_bag, run_record_path

    if not args.topic:
        raise CommandError("--bag needs --topic (the PointCloud2 topic to label)")
    if (
        args.split is not None
        or args.sequences is not None
        or args.save_confidence
        or args.allow_partial
    ):
        raise CommandError(
            "--split, --sequences, --allow-partial and --save-confidence are for --dataset (a "
            "labelled bag always carries each point's confidence)"
        )
    fmt = args.bag_format or bag_format(args.bag)
    check_target(args.out, fmt, overwrite=args.overwrite, source=args.bag)
    with open_bag(args.bag) as bag:
        bag.cloud_topic(args.topic)  # a wrong topic is told before the network loads
    predictor = predictor_from_args(args)
    overrides = parse_field_overrides(args.field, record=predictor.profile.points)
    summary = label_bag(
        predictor,
        args.bag,
        args.topic,
        args.out,
        target_format=fmt,
        overrides=overrides,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    print(summary.text())
    if not summary.ok:
        raise CommandError(
            f"{len(summary.failed)} of {summary.messages} {args.topic} messages could not be "
            f"labelled (written through unchanged; see {run_record_path(args.out)})",
            [f["reason"] for f in summary.failed],
        )
    return 0
