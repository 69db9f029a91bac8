"""`rangeret predict --files PATH... --out DIR`: label point-cloud files (PCD, PLY, LAS/LAZ, .bin).

Each PATH is a file, or a folder whose files with a known extension (`.pcd`, `.ply`, `.las`,
`.laz`, `.bin`) are read, not its subfolders. A file named on the command line may have any
extension: its format is then told from its first bytes (`rangeret.io.point_files`). For each
input, DIR gets `<stem>.label` (uint32 raw ids, one per point in the file's order), with
`--save-confidence` `<stem>.npy` (float16 confidences) and with `--write-labelled`
`<stem>.labelled.<ext>`: the file again in its own format and encoding with `label` and
`confidence` added (a `.bin` has no room for them: its `.label` is its labelled form). Files are
labelled one at a time. A file that cannot be read or labelled is reported and the others still
run; the command then exits 1 naming every failure. DIR/run.json records the network and, for
each file, its format, points, invalid points and which field (or fill value) gave each value.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from rangeret.cli.shared import predictor_from_args
from rangeret.commands import CommandError
from rangeret.exceptions import MissingExtraError, RangeRetError
from rangeret.inference.clouds import label_cloud
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import RunSummary
from rangeret.inference.timing import StageTimes
from rangeret.io.point_fields import parse_field_overrides, to_record
from rangeret.io.point_files import EXTENSIONS, read_point_file, write_labelled
from rangeret.io.run_info import write_run_info
from rangeret.io.scans import write_confidence, write_labels

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


def output_paths(out: Path, path: Path) -> dict[str, Path]:
    """Where the outputs of input `path` go: labels, confidences and the labelled copy's stem."""
    return {
        "labels": out / f"{path.stem}.label",
        "confidence": out / f"{path.stem}.npy",
        "labelled": out / f"{path.stem}.labelled",
    }


def predict_file(
    predictor: Predictor,
    path: Path,
    out: Path,
    *,
    overrides: Mapping[str, str],
    save_confidence: bool,
    labelled: bool,
    times: StageTimes | None = None,
) -> dict[str, Any]:
    """Label one file into `out`; what run.json records of it. Bad input raises the
    RangeRetError naming the file."""
    profile = predictor.profile
    times = times if times is not None else StageTimes()
    with times.stage("read"):
        point_file = read_point_file(path, record=profile.points)
        cloud = to_record(
            point_file.columns,
            record=profile.points,
            source=str(path),
            reflectance_fill=profile.reflectance_fill,
            overrides=overrides,
        )
    found = label_cloud(predictor, cloud, times)
    targets = output_paths(out, path)
    written = {"labels": str(targets["labels"])}
    with times.stage("write"):
        write_labels(targets["labels"], found.labels)
        if save_confidence:
            write_confidence(targets["confidence"], found.confidence)
            written["confidence"] = str(targets["confidence"])
        if labelled and point_file.can_write_labelled:
            target = targets["labelled"].with_name(targets["labelled"].name + point_file.extension)
            write_labelled(target, point_file, found.labels, found.confidence)
            written["labelled"] = str(target)
    info = point_file.describe()
    return {"file": str(path), **info, **cloud.describe(), "outputs": written}


def _problem(exc: Exception, path: Path) -> str:
    """An error's message without the leading file name the report puts before it."""
    text = str(exc)
    return text.removeprefix(f"{path}: ")


def run_files(args: argparse.Namespace) -> int:
    """Label every file of --files into --out (see the module docstring)."""
    if args.split is not None or args.sequences is not None:
        raise CommandError("--split and --sequences are for --dataset, not --files")
    files = collect_inputs(args.files)
    predictor = predictor_from_args(args)
    profile = predictor.profile
    overrides = parse_field_overrides(args.field, record=profile.points)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    summary = RunSummary(total=len(files))
    inputs: list[dict[str, Any]] = []
    start = time.perf_counter()
    for path in tqdm(files, desc="predict", unit="file", disable=args.quiet):
        try:
            entry = predict_file(
                predictor,
                path,
                out,
                overrides=overrides,
                save_confidence=args.save_confidence,
                labelled=args.write_labelled,
                times=summary.times,
            )
        except MissingExtraError:
            raise  # no file of its format can be read: one line, not one failure per file
        except RangeRetError as exc:
            summary.add(str(path), _problem(exc, path))
            inputs.append({"file": str(path), "error": _problem(exc, path)})
            continue
        summary.add(str(path), None, entry["points"])
        inputs.append(entry)
    summary.seconds = time.perf_counter() - start
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
    )
    print(summary.text())
    if not summary.ok:
        raise CommandError(
            f"{len(summary.failed)} of {summary.total} files could not be labelled "
            f"(every other file was written to {out})",
            [f"{k}: {v}" for k, v in summary.failed.items()],
        )
    return 0
