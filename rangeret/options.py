"""Command-line options shared by every entry point, written once so each takes them the same way.

`rangeret` subcommands, `rangeret serve` / `python -m service` and `python -m workers.predict_job`
all build their parsers from these. The network options are derived from `InferenceSpec`'s
fields (`rangeret.inference.spec`), which `InferenceSpec.from_args` reads back and checks.
Torch-free: the network is loaded only when a command runs.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.commands import CommandError
from rangeret.dataset.labels import load_label_config
from rangeret.dataset.layout import missing_sequences, resolve_sequences
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.spec import WEIGHTS, add_spec_options, group_fields
from rangeret.io.decode_limits import DECODED_OPTION, DEFAULT_MAX_DECODED_BYTES, DecodeLimits
from rangeret.submission.leaderboard import DEFAULT_NAME, DEFAULT_URL, LeaderboardEntry

if TYPE_CHECKING:
    from rangeret.adapt.tree import AdaptPlan

log = logging.getLogger("rangeret")


def add_output_options(parser: argparse.ArgumentParser) -> None:
    """-q (no progress bars) and -v (debug logging)."""
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def add_selection(
    parser: argparse.ArgumentParser,
    *,
    required: bool = True,
    partial_help: str = "",
) -> None:
    """--split or --sequences, exactly one of them (at most one where not `required`),
    --allow-partial (`partial_help` adds what else it allows in this command) and --version.

    The split names are the profile's, checked once the profile is known (`selected_sequences`).
    """
    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument(
        "--split",
        metavar="SPLIT",
        help="an official split of the profile: train, valid or test for SemanticKITTI (nuScenes: "
        "train, val, test, mini_train or mini_val)",
    )
    group.add_argument(
        "--sequences",
        nargs="+",
        metavar="XX",
        help="sequence folder names (also data outside the official splits; nuScenes: scene "
        "names such as scene-0103); each must be there",
    )
    parser.add_argument(
        "--version",
        metavar="VERSION",
        help="a nuScenes tree's version folder, such as v1.0-mini (default: the one ROOT holds)",
    )
    parser.add_argument(
        "--allow-partial",
        action="store_true",
        help="with --split: work on those of the split's sequences the dataset holds, naming the "
        "missing ones (without it a split with missing sequences is refused)" + partial_help,
    )


def selected_sequences(
    args: argparse.Namespace,
    profile: DatasetProfile,
    root: Path | str | None = None,
    *,
    doing: str = "using",
) -> list[str]:
    """The sequences chosen by --split or --sequences, as the profile writes their ids on disk
    (`--sequences 1` is "01" for SemanticKITTI, "001" for PandaSet).

    With the dataset `root`, a split whose sequences are not all there is a CommandError naming
    the missing ones, unless --allow-partial: then one warning names them and says what the
    command is `doing` with the others ("predicting 11, 12"). Named --sequences are not checked
    here: each missing one is an error where the scans are listed.
    """
    sequences = resolve_sequences(
        split=args.split, sequences=args.sequences, labels=profile.labels, layout=profile.layout
    )
    if root is None or args.split is None or not Path(root).is_dir():
        return sequences  # a missing root is named where the scans are listed
    missing = missing_sequences(
        root, sequences, layout=profile.layout, version=getattr(args, "version", None)
    )
    if not missing:
        return sequences
    present = [s for s in sequences if s not in missing]
    absent = f"the {args.split} split's sequences {', '.join(missing)} are not in {root}"
    if not present:
        raise CommandError(
            f"none of the {args.split} split's sequences ({', '.join(sequences)}) is in {root}"
        )
    if not getattr(args, "allow_partial", False):
        raise CommandError(
            f"{absent} (it holds {', '.join(present)}); pass --allow-partial to go on with "
            "those, or name them with --sequences"
        )
    log.warning("--allow-partial: %s; %s %s", absent, doing, ", ".join(present))
    return present


def selected_dataset(
    args: argparse.Namespace, profile: DatasetProfile, root: Path, *, doing: str = "using"
) -> DatasetSelection:
    """The dataset selection of --dataset ROOT, --split or --sequences, --version and
    --panoptic, made once where a command starts: the sequences as `selected_sequences` checks
    them."""
    version = getattr(args, "version", None)
    profile.layout.check_version(version)
    sequences = selected_sequences(args, profile, root, doing=doing)
    panoptic = bool(getattr(args, "panoptic", False))
    return DatasetSelection(
        Path(root), tuple(sequences), profile.layout, args.split, version, panoptic
    )


def add_offset_option(parser: argparse.ArgumentParser, help: str) -> None:
    """--sensor-offset DX DY DZ (metres, default 0 0 0): where a sensor sits from another, as
    `simulate` and `adapt` take it."""
    parser.add_argument(
        "--sensor-offset",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 0.0),
        metavar=("DX", "DY", "DZ"),
        help=help,
    )


def add_adapt_options(p: argparse.ArgumentParser) -> None:
    """The options of an adapt run (`rangeret adapt`, `python -m workers.adapt_job`): dataset,
    profiles, output, selection, offset, label map and --overwrite."""
    p.add_argument(
        "--dataset", type=Path, required=True, metavar="ROOT", help="the labelled source dataset"
    )
    p.add_argument(
        "--profile",
        required=True,
        metavar="SOURCE",
        help="the source dataset's profile: a built-in name or a YAML file",
    )
    p.add_argument(
        "--to-profile",
        required=True,
        metavar="TARGET",
        help="the target sensor's profile (its beams, image, range, reflectance scale, record, "
        "labels and layout): a built-in name or a YAML file",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="OUT",
        help="the adapted dataset's root, outside ROOT (and not holding it)",
    )
    add_selection(p)
    add_offset_option(
        p,
        "where the target sensor sits in the source sensor's frame (m: forward, left, up; "
        "default 0 0 0): every point moves by minus this offset",
    )
    p.add_argument(
        "--label-map",
        type=Path,
        metavar="MAP.yaml",
        help="a YAML mapping `source raw id: target raw id` (many to one); without it raw ids "
        "are kept and must be the target profile's",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="adapt every chosen scan again and replace its outputs, also where OUT/adapt.json "
        "records other settings (without it, scans already adapted with these settings are "
        "kept); the dataset itself is never written",
    )


def adapt_plan_from_args(args: argparse.Namespace) -> AdaptPlan:
    """The adapt run the options of `add_adapt_options` ask for: profiles, offset and label map
    checked, scans listed and `OUT/adapt.json` begun (`plan_adaptation`); every driver of
    `adapt` starts here. `rangeret.adapt` loads only then, so that parsers stay light."""
    from rangeret.adapt.resample import check_offset, check_profiles
    from rangeret.adapt.tree import AdaptSettings, plan_adaptation
    from rangeret.dataset.label_map import load_label_map

    if args.version is not None:
        raise CommandError("--version is for a dataset of tables; adapt reads folders of sequences")
    source, target = load_profile(args.profile), load_profile(args.to_profile)
    check_profiles(source, target)
    settings = AdaptSettings(
        source,
        target,
        check_offset(args.sensor_offset),
        None if args.label_map is None else load_label_map(args.label_map, target),
    )
    sequences = selected_sequences(args, source, args.dataset, doing="adapting")
    return plan_adaptation(args.dataset, args.out, sequences, settings, overwrite=args.overwrite)


def add_profile_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--profile NAME|FILE: the dataset profile (sensor, point record, labels, layout, splits)."""
    add_spec_options(parser, ("profile",))


def requested_profile(args: argparse.Namespace) -> DatasetProfile | None:
    """The profile of --profile, or None when it was not given (a checkpoint may then choose)."""
    name = getattr(args, "profile", None)
    return load_profile(name) if name else None


def profile_from_args(args: argparse.Namespace) -> DatasetProfile:
    """The profile of --profile (default semantickitti: the command line is where the default
    applies) with --label-config in its labels' place; a bad file is a LabelConfigError."""
    profile = requested_profile(args) or load_profile(None)
    path = getattr(args, "label_config", None)
    if path:
        profile = profile.with_overrides(labels=load_label_config(path))
    return profile


def add_field_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--field NAME=FIELD: which field of a file or message fills a value of the point record."""
    parser.add_argument(
        "--field",
        action="append",
        metavar="NAME=FIELD",
        default=[],
        help="read the point record's value NAME (x, y, z, remission, intensity, laser_id) from "
        "the cloud's field FIELD; by default each is found by its name or a usual alias "
        "(intensity for remission, ring for laser_id); repeatable",
    )


def add_decoded_limit_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--max-decoded-bytes N: the most a point-cloud file may decode to (the gateway's default)."""
    parser.add_argument(
        DECODED_OPTION,
        type=_positive_int,
        metavar="N",
        default=None,
        help="the most bytes a point-cloud file may decode to: its declared points times the "
        "wider of its point and the profile's record, checked from its header before it is "
        f"read whole (default {DEFAULT_MAX_DECODED_BYTES:,}, as the gateway's "
        "RANGERET_MAX_DECODED_BYTES)",
    )


def decode_limits_from_args(args: argparse.Namespace) -> DecodeLimits:
    """The bounds files are decoded within: --max-decoded-bytes, else the default."""
    given = getattr(args, "max_decoded_bytes", None)
    return DecodeLimits(max_decoded_bytes=given or DEFAULT_MAX_DECODED_BYTES)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_label_config(parser: argparse.ArgumentParser) -> None:
    """--label-config FILE: another label configuration than the bundled SemanticKITTI one."""
    parser.add_argument(
        "--label-config",
        type=Path,
        metavar="FILE",
        help="label configuration (.json of this project or an official semantic-kitti .yaml); "
        "default: the profile's",
    )


def add_leaderboard_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--method-name, --pdf-url, --code-url: the first three lines of an archive's description.txt,
    which the benchmark's leaderboard shows."""
    parser.add_argument(
        "--method-name",
        metavar="NAME",
        help=f"the method's name on the leaderboard (default: {DEFAULT_NAME})",
    )
    parser.add_argument(
        "--pdf-url", metavar="URL", help=f"link to the method's paper (default: {DEFAULT_URL})"
    )
    parser.add_argument(
        "--code-url", metavar="URL", help=f"link to the method's code (default: {DEFAULT_URL})"
    )


def leaderboard_from_args(args: argparse.Namespace) -> LeaderboardEntry:
    """The leaderboard entry of --method-name, --pdf-url and --code-url (defaults for the missing
    ones); a value on more than one line is a CommandError naming its option."""
    try:
        return LeaderboardEntry.from_values(args.method_name, args.pdf_url, args.code_url)
    except ValueError as exc:
        raise CommandError(str(exc)) from exc


def add_precision_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--precision auto|fp32|fp16|bf16: the forward pass's precision."""
    add_spec_options(parser, ("precision",))


def add_weights_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--checkpoint, --profile, --model and the projection options: which weights load, and for
    which sensor (every command that loads a network, `rangeret export` included)."""
    add_spec_options(parser, group_fields(WEIGHTS))


def add_network_options(parser: argparse.ArgumentParser) -> None:
    """Every field of `InferenceSpec` as an option, in the group "network": the options shared by
    every command that runs a network (predict, serve, the Ray job, the ROS 2 node), which
    `InferenceSpec.from_args` reads back."""
    add_spec_options(parser.add_argument_group("network"))
