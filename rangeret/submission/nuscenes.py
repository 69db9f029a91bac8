"""nuScenes-lidarseg and nuScenes-panoptic submission archives, written and checked as the
challenges' servers take them.

The archive holds the devkit's results folder at its top:

    lidarseg/<split>/<sample_data token>_lidarseg.bin   one uint8 class 1-16 per point, a file
                                                        for every keyframe of the split
    <split>/submission.json                             {"meta": {"use_camera": ..., "use_lidar":
                                                        ..., "use_radar": ..., "use_map": ...,
                                                        "use_external": ...}} (five booleans),
                                                        and the method under "method"
    description.txt                                     the method's name, links and checkpoint

nuScenes-panoptic's (`PANOPTIC_RESULTS`) is the same with `panoptic/<split>/<token>_panoptic.npz`
files (one uint16 array `data`: 1000 x class 1-16 + instance) and a meta that also names its
`task`, "segmentation". Each `ResultsFormat` says what differs.

`write_nuscenes_results` zips the same folder for any keyframes (a gateway job's), each in the
split folder its prediction lies in, with the same writer.

The validator makes every check of the devkit's `validate_submission` (the folders, the meta
keys and their types, a file for every sample of the split, its point count: the ground truth's
where the version has labels, else the sweep's, and values 1..C-1), each failure one line naming
the file, and more: unsafe zip entries, and a `test` archive with fewer than the official 6,008
samples of 150 scenes unless `allow_partial` (the devkit only compares with the tables it is
given, so a partial local test set passes it and the server refuses the archive).
"""

from __future__ import annotations

import json
import threading
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import cast

from tqdm import tqdm

from rangeret.dataset.layout import DatasetLayoutError, ScanEntry, discover
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.table_layout import TableLayout, prediction_split
from rangeret.io.atomic import atomic_path
from rangeret.io.scans import ScanFormatError, scan_num_points
from rangeret.io.zipfiles import DeflatedFile, ReproducibleZip, deflate_file, map_ahead
from rangeret.submission.archives import (
    DESCRIPTION_NAME,
    SubmissionCheck,
    SubmissionError,
    description_warnings,
    instance_problem,
    unsafe_entry,
)
from rangeret.submission.nuscenes_format import (
    LIDARSEG_RESULTS,
    MAX_META_BYTES,
    META_KEYS,
    PANOPTIC_RESULTS,
    ResultsFormat,
    SubmissionMeta,
    meta_problems,
    required_directories,
    submission_json,
    values_problem,
)

__all__ = [
    "LIDARSEG_RESULTS",
    "META_KEYS",
    "PANOPTIC_RESULTS",
    "ResultsFormat",
    "SubmissionMeta",
    "submission_json",
    "validate_nuscenes_submission",
    "write_nuscenes_results",
    "write_nuscenes_submission",
]

#: The official nuScenes-lidarseg test split: scenes and keyframes.
TEST_SCENES = 150
TEST_SAMPLES = 6008


def _tables_layout(profile: DatasetProfile) -> TableLayout:
    """The profile's layout of tables (a layout of folders has no `open`)."""
    if profile.layout.folders is not None:
        raise SubmissionError([f"profile {profile.name} does not read nuScenes tables"])
    return cast(TableLayout, profile.layout)


def _split_scans(
    dataset: Path,
    split: str,
    profile: DatasetProfile,
    version: str | None,
    allow_partial: bool,
    results: ResultsFormat,
) -> tuple[list[ScanEntry], list[str], list[str], bool]:
    """The keyframes of the split that the tables hold, its scenes present, problems with
    completeness, and whether the version has ground truth (which then gives the counts)."""
    layout = _tables_layout(profile)
    try:
        scenes = list(profile.labels.split(split))
        tables = layout.open(dataset, version)
    except (DatasetLayoutError, ValueError) as exc:
        return [], [], [str(exc)], False
    labelled = tables.has_panoptic if results.panoptic else tables.has_lidarseg
    found = discover(
        dataset,
        scenes,
        with_labels=labelled,
        missing_ok=True,
        layout=layout,
        version=tables.version,
        split=split,
        panoptic=results.panoptic,
    )
    problems = list(found.problems)
    missing = [s for s in scenes if s not in tables.scenes]
    if missing and not allow_partial:
        shown = ", ".join(missing[:5]) + (
            f" and {len(missing) - 5} more" if len(missing) > 5 else ""
        )
        problems.append(
            f"{tables.table_dir} lacks {len(missing)} of the {len(scenes)} scenes of the {split} "
            f"split ({shown}); the devkit refuses a split whose scenes are not all in the tables"
        )
    short = len(found.sequences) < TEST_SCENES or len(found.scans) < TEST_SAMPLES
    if split == "test" and not allow_partial and short:
        problems.append(
            f"{tables.table_dir} holds {len(found.scans):,} test samples of "
            f"{len(found.sequences)} scenes, but the official test split has {TEST_SAMPLES:,} "
            f"of {TEST_SCENES}: the local copy is incomplete, so the server would refuse the "
            "archive (--allow-partial is for testing only)"
        )
    return found.scans, found.sequences, problems, labelled


def _expected_points(entry: ScanEntry, profile: DatasetProfile) -> int:
    """What the devkit compares a prediction's length with: the ground truth's where there is
    one, else the sweep's points."""
    if entry.label_path is not None:
        return entry.label_file.count(entry.label_path)
    return scan_num_points(entry.scan_path, record=profile.points)


def write_nuscenes_submission(
    predictions: Path | str,
    dataset: Path | str,
    out: Path | str,
    split: str = "test",
    *,
    profile: DatasetProfile,
    meta: SubmissionMeta,
    submission: str,
    description: str,
    version: str | None = None,
    allow_partial: bool = False,
    progress: bool = False,
    workers: int | None = None,
    results: ResultsFormat = LIDARSEG_RESULTS,
) -> SubmissionCheck:
    """Build the zip of the predictions of every keyframe of `split` (`PRED/lidarseg/<split>/`,
    or the `results` format's folder),
    with `submission` as `<split>/submission.json` and `description` as `description.txt`.

    Raises `SubmissionError` listing every missing or wrong prediction (and an incomplete local
    test set unless `allow_partial`), writing nothing; the archive is validated before it is
    moved into place and is the same bytes for the same inputs whatever the `workers`.
    """
    predictions, dataset, out = Path(predictions), Path(dataset), Path(out)
    if out.suffix != ".zip":
        raise SubmissionError([f"{out}: the archive's name must end with .zip"])
    scans, _, problems, _ = _split_scans(dataset, split, profile, version, allow_partial, results)
    if not scans and not problems:
        problems.append(f"{dataset} holds no sample of the {split} split")
    with atomic_path(out, suffix=".zip") as tmp:
        _write_results(
            tmp,
            predictions,
            {split: scans},
            submission,
            description,
            profile=profile,
            problems=problems,
            workers=workers,
            progress=progress,
            results=results,
        )
        check = validate_nuscenes_submission(
            tmp,
            dataset,
            split,
            profile=profile,
            version=version,
            allow_partial=allow_partial,
            results=results,
        )
        check.path = out
        check.raise_for_problems()
    return check


def write_nuscenes_results(
    predictions: Path | str,
    scans: Sequence[ScanEntry],
    out: Path | str,
    *,
    profile: DatasetProfile,
    submission: str,
    description: str,
    workers: int | None = None,
    results: ResultsFormat = LIDARSEG_RESULTS,
) -> None:
    """Zip the results folder of the keyframes `scans` (of any scenes) at `out`: each split
    folder their predictions lie in (`PRED/lidarseg/<split>/`, or the `results` format's) with
    its `submission.json`.

    Raises `SubmissionError` listing every missing or wrong prediction, writing nothing; unlike
    `write_nuscenes_submission`, a split's other keyframes are not asked for.
    """
    splits: dict[str, list[ScanEntry]] = {}
    for entry in scans:
        splits.setdefault(prediction_split(entry), []).append(entry)
    problems = [] if scans else [f"there is no keyframe to put in {out}"]
    with atomic_path(Path(out), suffix=".zip") as tmp:
        _write_results(
            tmp,
            Path(predictions),
            splits,
            submission,
            description,
            profile=profile,
            problems=problems,
            workers=workers,
            results=results,
        )


def _write_results(
    path: Path,
    predictions: Path,
    splits: Mapping[str, Sequence[ScanEntry]],
    submission: str,
    description: str,
    *,
    profile: DatasetProfile,
    problems: list[str],
    workers: int | None,
    progress: bool = False,
    results: ResultsFormat = LIDARSEG_RESULTS,
) -> None:
    """Write the zip at `path`: the folders of each split, every keyframe's prediction, then
    each split's submission.json and description.txt; `SubmissionError` with `problems` and
    every missing or wrong prediction (the zip then holds no file)."""
    failed = threading.Event()
    if problems:
        failed.set()
    num_classes = profile.num_classes
    named = [(split, entry) for split, entries in splits.items() for entry in entries]

    def read(item: tuple[str, ScanEntry]) -> tuple[str | None, DeflatedFile | None]:
        split, entry = item
        try:
            num_points = _expected_points(entry, profile)
        except ScanFormatError as exc:
            return str(exc), None
        pred = entry.prediction_in(predictions)
        if not pred.is_file():
            return f"{pred} is missing (no prediction for sample_data {entry.key})", None
        data = pred.read_bytes()
        problem = values_problem(data, str(pred), num_points, num_classes, results)
        if problem or failed.is_set():
            return problem, None
        return None, deflate_file(results.entry_name(split, entry), data)

    with ReproducibleZip(path) as zf:
        folders = (name for split in splits for name in required_directories(split, results))
        for name in dict.fromkeys(folders):
            zf.add_directory(name)
        for problem, file in tqdm(
            map_ahead(read, named, workers),
            total=len(named),
            desc="submission",
            unit="scan",
            disable=not progress,
        ):
            if problem:
                problems.append(problem)
                failed.set()
            elif file is not None and not problems:
                zf.add_deflated(file)
        if not problems:
            for split in splits:
                zf.add_file(f"{split}/submission.json", submission)
            zf.add_file(DESCRIPTION_NAME, description.rstrip("\n") + "\n")
    if problems:
        raise SubmissionError(problems)


def validate_nuscenes_submission(
    archive: Path | str,
    dataset: Path | str,
    split: str,
    *,
    profile: DatasetProfile,
    version: str | None = None,
    allow_partial: bool = False,
    progress: bool = False,
    results: ResultsFormat = LIDARSEG_RESULTS,
) -> SubmissionCheck:
    """Check a nuScenes-lidarseg zip (or the `results` format's) against the version's tables
    for `split`: every check of the devkit's validator, each failure one line naming the file,
    and the project's own (a panoptic archive must hold objects)."""
    archive, dataset = Path(archive), Path(dataset)
    check = SubmissionCheck(path=archive, partial=allow_partial)
    if archive.suffix != ".zip":
        check.problems.append(f"{archive}: the archive's name must end with .zip")
    if not archive.is_file():
        check.problems.append(f"{archive} does not exist")
        return check
    scans, present, dataset_problems, _ = _split_scans(
        dataset, split, profile, version, allow_partial, results
    )
    check.sequences = present
    check.problems += dataset_problems
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as exc:
        check.problems.append(f"{archive} is not a readable zip archive ({exc})")
        return check
    with zf:
        entries: dict[str, zipfile.ZipInfo] = {}
        for info in zf.infolist():
            problem = unsafe_entry(info)
            if problem:
                check.problems.append(f"{archive}: entry {info.filename!r} {problem}")
            elif info.filename in entries:
                check.problems.append(f"{archive}: entry {info.filename!r} appears more than once")
            entries[info.filename] = info
        names = set(entries)
        meta_name = f"{split}/submission.json"
        bins = f"{results.folder}/{split}/"
        if not any(n.startswith(f"{split}/") for n in names):
            check.problems.append(
                f"{archive}: the folder {split}/ (which holds submission.json) does not exist"
            )
        elif meta_name not in names:
            check.problems.append(f"{archive}: {meta_name} does not exist")
        elif entries[meta_name].file_size > MAX_META_BYTES:
            check.problems.append(
                f"{archive}: {meta_name} is {entries[meta_name].file_size:,} bytes, more than "
                f"the {MAX_META_BYTES:,} a submission.json may have"
            )
        else:
            try:
                data = json.loads(zf.read(entries[meta_name]).decode("utf-8"))
            except RecursionError:
                check.problems.append(f"{archive}: {meta_name} is not JSON (it nests too deeply)")
            except (zipfile.BadZipFile, OSError, ValueError) as exc:
                check.problems.append(f"{archive}: {meta_name} is not JSON ({exc})")
            else:
                check.problems += meta_problems(data, f"{archive}: {meta_name}", results)
        if not any(n.startswith(bins) for n in names):
            kind = results.suffix.rsplit(".", 1)[-1]
            check.problems.append(
                f"{archive}: the folder {bins} (which holds the .{kind} files) does not exist"
            )
        counts = [0, 0]
        check.warnings += description_warnings(zf, entries.get(DESCRIPTION_NAME), archive)
        for entry in tqdm(scans, desc="validate", unit="scan", disable=not progress):
            name = results.entry_name(split, entry)
            info = entries.get(name)
            if info is None:
                check.problems.append(
                    f"{archive}: {name} does not exist (sample_data {entry.name} of {entry.sequence})"
                )
                continue
            try:
                num_points = _expected_points(entry, profile)
                if info.file_size > results.most_bytes(num_points):
                    check.problems.append(
                        f"{archive}: {name} is {info.file_size:,} bytes, more than the "
                        f"{results.most_bytes(num_points):,} a prediction of {num_points:,} "
                        "points may take"
                    )
                    continue
                data = zf.read(info)
            except ScanFormatError as exc:
                check.problems.append(str(exc))
                continue
            except (zipfile.BadZipFile, OSError, ValueError) as exc:
                check.problems.append(f"{archive}: {name} cannot be read ({exc})")
                continue
            problem = values_problem(
                data,
                f"{archive}: {name}",
                num_points,
                profile.num_classes,
                results,
                profile.things,
                counts,
            )
            if problem:
                check.problems.append(problem)
            check.scans += 1
    refusal = instance_problem(archive, counts) if results.panoptic else None
    if refusal is not None:
        check.problems.append(refusal)
    return check
