"""`rangeret predict --files PATH... --out DIR`: label point-cloud files (PCD, PLY, LAS/LAZ, .bin).

Each PATH is a file, or a folder whose files with a known extension (`.pcd`, `.ply`, `.las`,
`.laz`, `.bin`) are read, not its subfolders. A file named on the command line may have any
extension: its format is then told from its first bytes (`rangeret.io.point_files`). For each
input, DIR gets `<stem>.label` (uint32 raw ids, one per point in the file's order; with
--panoptic the benchmark's panoptic labels), with `--save-confidence` `<stem>.npy` (float16
confidences) and with `--write-labelled` `<stem>.labelled.<ext>`: the file again in its own
format and encoding with `label` (the raw ids) and `confidence` added, and with --panoptic
`instance` (a `.bin` has no room for them: its `.label` is its labelled form). Files are
labelled one at a time, each within --max-decoded-bytes (what its header declares it decodes to,
checked before it is read whole). A file that cannot be read or labelled is reported and the
others still run; the command then exits 1 naming every failure. DIR/run.json records the network
and, for each file, its format, points, invalid points and which field (or fill value) gave each
value; its `runs` lists every run into DIR. Labelling into a DIR of another checkpoint's labels,
or of the other task's (panoptic or semantic), is refused before any file is read unless
--overwrite.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from rangeret.cli.shared import predictor_from_args
from rangeret.commands import CommandError
from rangeret.io.point_fields import parse_field_overrides
from rangeret.io.point_files import EXTENSIONS
from rangeret.io.run_info import check_weights, started_now, write_run_info
from rangeret.options import decode_limits_from_args

RUNNER = "rangeret predict --files"


def collect_inputs(paths: Sequence[Path]) -> list[Path]:
    """The files to label: each file given, and each folder's files with a known extension
    (sorted, not recursive); a missing path, an empty folder, or two inputs with one stem (their
    outputs would collide) is a CommandError naming them."""
    files: list[Path] = []
    for path in paths:
        if path.is_dir():
            found = sorted(
                p for p in path.iterdir() if p.is_file() and p.suffix.lower() in EXTENSIONS
            )
            if not found:
                raise CommandError(
                    f"--files {path}: the folder holds no {', '.join(EXTENSIONS)} file"
                )
            files += found
        elif path.is_file():
            files.append(path)
        else:
            raise CommandError(f"--files {path}: no such file or folder")
    by_stem: dict[str, Path] = {}
    for path in files:
        other = by_stem.setdefault(path.stem, path)
        if other != path:
            raise CommandError(
                f"--files: {other} and {path} have the same stem {path.stem!r}, so their outputs "
                "would be the same files; rename one or label them into different --out folders"
            )
    return files


def run_files(args: argparse.Namespace) -> int:
    """Label every file of --files into --out (see the module docstring)."""
    from rangeret.inference.files_runner import label_files

    if args.split is not None or args.sequences is not None or args.allow_partial:
        raise CommandError(
            "--split, --sequences and --allow-partial are for --dataset, not --files"
        )
    started = started_now()
    files = collect_inputs(args.files)
    predictor = predictor_from_args(args)
    profile = predictor.profile
    overrides = parse_field_overrides(args.field, record=profile.points)
    out: Path = args.out
    panoptic = predictor.clustering is not None
    check_weights(out, predictor.checkpoint_sha256, overwrite=args.overwrite, panoptic=panoptic)
    summary, inputs = label_files(
        predictor,
        files,
        out,
        overrides=overrides,
        save_confidence=args.save_confidence,
        labelled=args.write_labelled,
        progress=not args.quiet,
        limits=decode_limits_from_args(args),
    )
    write_run_info(
        out,
        predictor.describe(),
        runner=RUNNER,
        dataset=None,
        sequences=[],
        batch_size=1,
        inputs=inputs,
        extra={
            "reflectance_fill": profile.reflectance_fill,
            "point_record": list(profile.points.fields),
            "field_overrides": dict(overrides),
        },
        overwrite=args.overwrite,
        started=started,
    )
    print(summary.text())
    summary.raise_failures(out, unit="file", verb="labelled")
    return 0
