"""`rangeret predict`: label a dataset's scans into a predictions tree, point-cloud files into a
folder, or a bag's PointCloud2 messages into a labelled bag."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.cli.predict_bag import add_bag_options, run_bag
from rangeret.cli.shared import predictor_from_args
from rangeret.commands import CommandError
from rangeret.options import (
    add_decoded_limit_option,
    add_field_option,
    add_network_options,
    add_selection,
    selected_dataset,
)
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--dataset", type=Path, metavar="ROOT", help="a dataset tree (with --split or --sequences)"
    )
    source.add_argument(
        "--files",
        type=Path,
        nargs="+",
        metavar="PATH",
        help="point-cloud files (.pcd, .ply, .las, .laz, .bin) or folders holding them (not "
        "their subfolders); writes OUT/<stem>.label per file",
    )
    source.add_argument(
        "--bag", type=Path, metavar="IN", help="a rosbag2 folder or ROS 1 .bag file (with --topic)"
    )
    add_selection(p, required=False)
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="OUT",
        help="where to write: a predictions tree (--dataset), a folder (--files) or a bag (--bag)",
    )
    p.add_argument(
        "--save-confidence",
        action="store_true",
        help="also write each point's confidence (the softmax probability of its label at its "
        "pixel) as float16 in PRED/sequences/XX/confidence/NNNNNN.npy (nuScenes: "
        "PRED/confidence/<split>/<token>.npy; with --files: OUT/<stem>.npy)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="--dataset: predict every chosen scan again, replacing its prediction, also where "
        "OUT holds predictions from other weights (without it, scans already predicted are "
        "kept and a tree from other weights is refused); --files: label into a folder of other "
        "weights' labels; either way other predictions stay and OUT/run.json lists every run. "
        "--bag: replace an existing OUT and OUT.run.json",
    )
    add_bag_options(p)
    p.add_argument(
        "--write-labelled",
        action="store_true",
        help="with --files: also write each file again in its own format with label and "
        "confidence fields added, as OUT/<stem>.labelled.<ext>",
    )
    p.add_argument(
        "--label-map",
        type=Path,
        metavar="MAP.yaml",
        help="with --dataset: run the checkpoint on another sensor's dataset, --profile naming "
        "the data's profile: scans projected with that sensor, the network's own classes "
        "predicted and written as the data profile's raw ids through MAP (a YAML mapping "
        "`network raw id: data raw id`, as `rangeret adapt --label-map` takes)",
    )
    add_field_option(p)
    add_decoded_limit_option(p)
    add_network_options(p)


def run(args: argparse.Namespace) -> int:
    """Predict the scans of the source chosen (a dataset's split or sequences, files, or a bag)."""
    if args.label_map is not None and args.dataset is None:
        raise CommandError("--label-map is for --dataset")
    if args.max_decoded_bytes is not None and args.files is None:
        raise CommandError("--max-decoded-bytes is for --files")
    if args.bag is None:
        for option, value in (("--topic", args.topic), ("--bag-format", args.bag_format)):
            if value:
                raise CommandError(f"{option} is for --bag")
    elif args.write_labelled:
        raise CommandError("--write-labelled is for --files (a labelled bag carries its labels)")
    else:
        return run_bag(args)
    if args.files is not None:
        from rangeret.cli.predict_files import run_files

        return run_files(args)
    if args.write_labelled:
        raise CommandError("--write-labelled is for --files")
    if args.field:
        raise CommandError(
            "--field maps the fields of point-cloud files and bags, not of --dataset scans"
        )
    if args.split is None and args.sequences is None:
        raise CommandError("--dataset needs --split or --sequences")
    if args.version is not None and args.dataset is None:
        raise CommandError("--version is for --dataset")
    if args.label_map is not None and args.profile is None:
        raise CommandError("--label-map needs --profile naming the profile of the dataset's sensor")
    return run_dataset(args)


def run_dataset(args: argparse.Namespace) -> int:
    """Predict every scan of a split or of chosen sequences into a predictions tree."""
    from rangeret.inference.runner import predict_tree

    predictor = predictor_from_args(args)
    selection = selected_dataset(args, predictor.profile, args.dataset, doing="predicting")
    summary = predict_tree(
        predictor,
        selection,
        args.out,
        batch_size=args.batch_size,
        progress=not args.quiet,
        save_confidence=args.save_confidence,
        overwrite=args.overwrite,
    )
    print(summary.text())
    summary.raise_failures(args.out)
    return 0


COMMAND = Subcommand(
    "predict",
    "label a dataset's scans, point-cloud files, or a bag's clouds",
    add_arguments,
    run,
)
