"""Command-line options shared by every entry point, written once so each takes them the same way.

`rangeret` subcommands, `rangeret serve` / `python -m service` and `python -m workers.predict_job`
all build their parsers from these. Torch-free: the network options are checked here and the
network is loaded only when a command runs.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.commands import CommandError
from rangeret.dataset.labels import load_label_config
from rangeret.dataset.layout import missing_sequences, resolve_sequences
from rangeret.dataset.profiles import BUILTIN_PROFILES, DatasetProfile, load_profile
from rangeret.extras import MissingExtraError
from rangeret.inference.runtime.backends import BACKENDS, check_backend
from rangeret.inference.runtime.precision import PRECISIONS
from rangeret.submission.leaderboard import DEFAULT_NAME, DEFAULT_URL, LeaderboardEntry

if TYPE_CHECKING:
    from rangeret.inference.predictor import PredictorSpec

log = logging.getLogger("rangeret")

#: The splits every label configuration names.
SPLITS = ("train", "valid", "test")


def add_output_options(parser: argparse.ArgumentParser) -> None:
    """-q (no progress bars) and -v (debug logging)."""
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def add_selection(
    parser: argparse.ArgumentParser,
    splits: Sequence[str] = SPLITS,
    *,
    required: bool = True,
    partial_help: str = "",
) -> None:
    """--split or --sequences, exactly one of them (at most one where not `required`), and
    --allow-partial (`partial_help` adds what else it allows in this command)."""
    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument(
        "--split", choices=list(splits), help="an official split of the label configuration"
    )
    group.add_argument(
        "--sequences",
        nargs="+",
        metavar="XX",
        help="sequence folder names (also data outside the official splits); each must be there",
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
    missing = missing_sequences(root, sequences, layout=profile.layout)
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


def add_profile_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--profile NAME|FILE: the dataset profile (sensor, point record, labels, layout, splits)."""
    parser.add_argument(
        "--profile",
        metavar="NAME|FILE",
        help=f"dataset profile: {', '.join(BUILTIN_PROFILES)} or a YAML file "
        "(`rangeret profile show NAME` prints one to start from); default: the checkpoint's, "
        "else semantickitti",
    )


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


def add_projection_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--height, --width, --fov-up, --fov-down: explicit values in place of the profile's (the
    project's own checkpoints fix their resolution)."""
    parser.add_argument("--height", type=int, help="range image rows (default: the profile's)")
    parser.add_argument("--width", type=int, help="range image columns (default: the profile's)")
    parser.add_argument(
        "--fov-up",
        type=float,
        metavar="DEG",
        help="upper vertical field of view (default: the profile's)",
    )
    parser.add_argument(
        "--fov-down",
        type=float,
        metavar="DEG",
        help="lower vertical field of view (default: the profile's)",
    )


def add_precision_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--precision auto|fp32|fp16|bf16: the forward pass's precision."""
    parser.add_argument(
        "--precision",
        default="auto",
        choices=list(PRECISIONS),
        help="precision of the network's passes; auto is fp16 on CUDA and fp32 on the CPU "
        "(default; always fp32 with --backend onnxruntime)",
    )


def add_weights_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--profile, --model, --checkpoint and the projection options: which weights load, and for
    which sensor (every command that loads a network, `rangeret export` included)."""
    add_profile_option(parser)
    parser.add_argument(
        "--model",
        choices=["rangeret-thesis", "rangeret-cir"],
        help="network name; recognised from the checkpoint when omitted",
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        metavar="FILE",
        help="weights: a published model's name (`rangeret weights list`: rangeret-kitti-657, "
        "rangeret-panda-600, rangeret-poss-528; fetched from the cache or the model hub, with "
        "its profile), the project's own checkpoint or a published .pt file (default: the "
        "bundled demo weights, trained on simulated scenes only)",
    )
    add_projection_options(parser)


def add_backend_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--backend torch|onnxruntime: where the network's forward pass runs."""
    parser.add_argument(
        "--backend",
        default="torch",
        choices=list(BACKENDS),
        help="run the network in torch (default) or in onnxruntime on its ONNX export, made "
        "once per checkpoint into $RANGERET_CACHE/onnx (else ~/.cache/rangeret/onnx); "
        "onnxruntime runs fp32 only, and on CUDA needs the onnxruntime-gpu package",
    )


def add_network_options(parser: argparse.ArgumentParser) -> None:
    """The options shared by every command that runs a network (predict, serve, the Ray job)."""
    g = parser.add_argument_group("network")
    add_weights_options(g)
    g.add_argument(
        "--batch-size",
        type=int,
        default=1,
        metavar="N",
        help="scans per network pass (default 1)",
    )
    g.add_argument(
        "--no-knn",
        action="store_true",
        help="take each point's pixel class, without kNN refinement",
    )
    g.add_argument(
        "--device",
        default="auto",
        choices=["auto", "cpu", "cuda"],
        help="auto picks CUDA when present (default)",
    )
    add_precision_option(g)
    add_backend_option(g)
    g.add_argument(
        "--tta-flip", action="store_true", help="test-time augmentation: add the mirrored view"
    )
    g.add_argument(
        "--tta-shifts",
        type=int,
        default=0,
        metavar="N",
        help="test-time augmentation: add N azimuth-rotated views",
    )


def spec_from_args(args: argparse.Namespace) -> PredictorSpec:
    """A `PredictorSpec` from the shared network options (checked, not loaded yet)."""
    from rangeret.inference.settings import KnnSettings, TtaSettings

    if args.batch_size < 1:
        raise CommandError(f"--batch-size must be at least 1, got {args.batch_size}")
    if args.tta_shifts < 0:
        raise CommandError(f"--tta-shifts must not be negative, got {args.tta_shifts}")
    try:
        check_backend(args.backend, args.precision)
    except MissingExtraError:
        raise
    except ValueError as exc:
        raise CommandError(str(exc)) from exc
    tta = (
        TtaSettings(flip=args.tta_flip, shifts=args.tta_shifts)
        if (args.tta_flip or args.tta_shifts)
        else None
    )
    return replace(
        weights_spec_from_args(args),
        device=args.device,
        precision=args.precision,
        knn=None if args.no_knn else KnnSettings(),
        tta=tta,
        backend=args.backend,
    )


def weights_spec_from_args(args: argparse.Namespace) -> PredictorSpec:
    """A `PredictorSpec` of the weights options (a published model's name fetched, with its
    profile, network and resolution), the run's own settings left at their defaults."""
    from rangeret.inference.predictor import PredictorSpec
    from rangeret.models.weights.demo import resolve_checkpoint
    from rangeret.models.weights.hub import resolve_weights

    weights = resolve_weights(
        args.checkpoint if args.checkpoint is not None else resolve_checkpoint(None),
        requested_profile(args),
        args.model,
        args.height,
        args.width,
    )
    return PredictorSpec(
        checkpoint=str(weights.path),
        model=weights.model,
        profile=weights.profile,
        height=weights.height,
        width=weights.width,
        fov_up=args.fov_up,
        fov_down=args.fov_down,
    )


#: The network options by name, as Serve application arguments and job submissions spell them:
#: each is the `dest` of its command-line option, except `knn` (a bool; `knn: false` is
#: `--no-knn`).
NETWORK_OPTIONS = (
    "checkpoint",
    "profile",
    "model",
    "height",
    "width",
    "fov_up",
    "fov_down",
    "batch_size",
    "knn",
    "device",
    "precision",
    "backend",
    "tta_flip",
    "tta_shifts",
)


def network_values(args: argparse.Namespace) -> dict[str, object]:
    """The network options a command was given, by name (see `NETWORK_OPTIONS`), those left
    unset omitted: what another process needs to build the same network."""
    values: dict[str, object] = {}
    for name in NETWORK_OPTIONS:
        value = (not args.no_knn) if name == "knn" else getattr(args, name, None)
        if value is None or (value is False and name == "tta_flip"):
            continue
        values[name] = str(value) if isinstance(value, Path) else value
    return values


def network_argv(values: dict[str, object]) -> list[str]:
    """The command-line options for network options by name (the inverse of `network_values`);
    an unknown name or a value of the wrong kind is a `CommandError` naming it."""
    unknown = sorted(set(values) - set(NETWORK_OPTIONS))
    if unknown:
        raise CommandError(
            f"unknown network option(s) {', '.join(unknown)}; the known ones are "
            f"{', '.join(NETWORK_OPTIONS)}"
        )
    argv: list[str] = []
    for name in NETWORK_OPTIONS:
        if name not in values or values[name] is None:
            continue
        value = values[name]
        flag = "--" + name.replace("_", "-")
        if name in ("knn", "tta_flip"):
            if not isinstance(value, bool):
                raise CommandError(f"the network option {name} is true or false, got {value!r}")
            if name == "knn" and not value:
                argv.append("--no-knn")
            elif name == "tta_flip" and value:
                argv.append(flag)
            continue
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise CommandError(
                f"the network option {name} takes a number or a string, got {value!r}"
            )
        argv += [flag, str(value)]
    return argv


def network_args(values: dict[str, object]) -> argparse.Namespace:
    """The parsed network options for options by name, checked as the command line checks them;
    a bad one is a `CommandError` naming it."""
    parser = argparse.ArgumentParser(prog="network options", add_help=False, exit_on_error=False)
    add_network_options(parser)
    argv = network_argv(values)
    try:
        args, unknown = parser.parse_known_args(argv)
    except argparse.ArgumentError as exc:
        raise CommandError(f"bad network option: {exc}") from exc
    if unknown:
        raise CommandError(f"bad network options: {' '.join(unknown)}")
    return args


def spec_from_values(values: dict[str, object]) -> PredictorSpec:
    """A `PredictorSpec` from network options by name (a published model's name resolved)."""
    return spec_from_args(network_args(values))
