"""SemanticKITTI semantic-segmentation submission archives (CodaLab / Codabench).

The server expects a zip with explicit directory entries `sequences/`, `sequences/NN/` and
`sequences/NN/predictions/` for NN = 11..21, and `sequences/NN/predictions/NNNNNN.label` (raw ids,
uint32) with one label per point of the matching test scan; `description.txt` is optional, but
its first three lines (`name:`, `pdf url:`, `code url:`, see `rangeret.submission.leaderboard`) are what the
leaderboard shows, so every archive written here has them and the validator warns without them.

The official validator compares the zip only with the local velodyne folders, so an incomplete
local copy of the test set passes it and the server then fails. Here the dataset is also checked
against the official scan counts of the test split, unless a partial archive is asked for
explicitly (for tests). Nothing is written unless the archive would pass; every missing or wrong
file is listed instead. The benchmark is SemanticKITTI's: its test scans are read with that
dataset's layout and point record, and the caller gives the label configuration (`labels`, the
semantickitti profile's).
"""

from __future__ import annotations

import re
import stat
import threading
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.layout import KITTI_LAYOUT, ScanEntry, discover
from rangeret.exceptions import DatasetError
from rangeret.io.atomic import atomic_path
from rangeret.io.scans import KITTI_RECORD, LABEL_BYTES, ScanFormatError, scan_num_points
from rangeret.io.zipfiles import DeflatedFile, ReproducibleZip, deflate_file, map_ahead
from rangeret.submission.leaderboard import (
    DEFAULT_NAME,
    DEFAULT_URL,
    LeaderboardEntry,
    description_problems,
)

#: Scans per sequence of the official SemanticKITTI test split (20,351 in all).
TEST_SCAN_COUNTS: dict[str, int] = {
    "11": 921, "12": 1061, "13": 3281, "14": 631, "15": 1901, "16": 1731,
    "17": 491, "18": 1801, "19": 4981, "20": 831, "21": 2721,
}  # fmt: skip
TEST_SEQUENCES: tuple[str, ...] = tuple(TEST_SCAN_COUNTS)

DESCRIPTION_NAME = "description.txt"
_LABEL_ENTRY = re.compile(r"^sequences/(\d\d)/predictions/([^/]+)\.label$")
_MAX_LISTED = 50


class SubmissionError(DatasetError, ValueError):
    """An archive (or the predictions for one) that the benchmark server would refuse."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = list(problems)
        shown = "; ".join(self.problems[:3])
        more = f" (and {len(self.problems) - 3} more)" if len(self.problems) > 3 else ""
        super().__init__(f"{len(self.problems)} problem(s): {shown}{more}")


@dataclass
class SubmissionCheck:
    """What a validation found: the scans checked and every problem, each naming its file, and
    warnings about what the server accepts but shows badly (the leaderboard's metadata)."""

    path: Path
    partial: bool
    sequences: list[str] = field(default_factory=list)
    scans: int = 0
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def raise_for_problems(self) -> None:
        """Raise `SubmissionError` if any problem was found."""
        if self.problems:
            raise SubmissionError(self.problems)

    def summary(self) -> str:
        """One paragraph for people: passed or not, what was checked, the first problems."""
        kind = "partial archive (for testing only)" if self.partial else "archive"
        if self.ok:
            lines = [
                f"{self.path}: valid {kind}; {self.scans:,} predictions checked over "
                f"{len(self.sequences)} sequence(s) ({', '.join(self.sequences)})"
            ]
            lines += [f"  warning: {w}" for w in self.warnings]
            return "\n".join(lines)
        lines = [f"{self.path}: INVALID {kind}, {len(self.problems)} problem(s):"]
        lines += [f"  - {p}" for p in self.problems[:_MAX_LISTED]]
        if len(self.problems) > _MAX_LISTED:
            lines.append(f"  ... and {len(self.problems) - _MAX_LISTED} more")
        return "\n".join(lines)


def _valid_id_table(config: LabelConfig) -> np.ndarray:
    table = np.zeros(1 << 16, dtype=bool)
    table[list(config.valid_prediction_ids)] = True
    return table


def _count_objects(data: bytes, thing_ids: np.ndarray, counts: list[int]) -> None:
    """Add a panoptic label file's thing points, and those of them with an instance (its high
    16 bits), to `counts`."""
    labels = np.frombuffer(data, dtype="<u4")
    thing = thing_ids[(labels & 0xFFFF).astype(np.intp)]
    counts[0] += int(thing.sum())
    counts[1] += int((thing & (labels >> 16 > 0)).sum())


def instance_problem(archive: Path | str, counts: Sequence[int]) -> str | None:
    """Why an archive of panoptic labels is refused for holding no object at all: its thing
    points (`counts[0]`) all without an instance (`counts[1]`): semantic labels in a panoptic
    archive."""
    if counts[0] and not counts[1]:
        return (
            f"{archive}: none of its {counts[0]:,} thing-class points has an instance: these are "
            "semantic labels, not panoptic ones (predict with --panoptic)"
        )
    return None


def _label_problem(data: bytes, name: str, num_points: int, valid: np.ndarray) -> str | None:
    """Why a prediction's bytes are wrong for a scan of `num_points` points, or None."""
    if len(data) != num_points * LABEL_BYTES:
        return (
            f"{name} holds {len(data) / LABEL_BYTES:g} labels but its scan has {num_points} points"
        )
    labels = np.frombuffer(data, dtype="<u4")
    low = (labels & 0xFFFF).astype(np.intp)
    bad = ~valid[low]
    if bad.any():
        ids = sorted({int(v) for v in low[bad][:1000]})[:8]
        return (
            f"{name} holds {int(bad.sum())} label(s) with raw ids the learning map's inverse "
            f"cannot produce (e.g. {ids}); predictions must be raw ids such as 10 (car) or 40 (road)"
        )
    return None


def _dataset_scans(
    dataset: Path, allow_partial: bool
) -> tuple[list[ScanEntry], list[str], list[str]]:
    """The test scans the dataset holds, the sequences present, and problems with completeness."""
    found = discover(dataset, TEST_SEQUENCES, missing_ok=allow_partial, layout=KITTI_LAYOUT)
    problems = list(found.problems)
    if not allow_partial:
        counts = {s: len(v) for s, v in found.by_sequence().items()}
        short = [
            f"{seq} ({counts[seq]:,} of {expected:,})"
            for seq, expected in TEST_SCAN_COUNTS.items()
            if counts.get(seq) not in (None, expected)
        ]
        if short:
            problems.append(
                f"{dataset}/sequences holds other scan counts than the official test set in "
                f"sequence{'s' if len(short) > 1 else ''} {', '.join(short)}: the local copy of "
                "the test set is incomplete, so the server would refuse the archive "
                "(--allow-partial is for testing only)"
            )
    return found.scans, found.sequences, problems


def _entry_name(entry: ScanEntry) -> str:
    return f"sequences/{entry.sequence}/predictions/{entry.name}.label"


def required_directories() -> Iterator[str]:
    """The directory entries every archive must hold, in order."""
    yield "sequences/"
    for seq in TEST_SEQUENCES:
        yield f"sequences/{seq}/"
        yield f"sequences/{seq}/predictions/"


def _read_prediction(
    entry: ScanEntry, predictions: Path, valid: np.ndarray, failed: threading.Event
) -> tuple[str | None, DeflatedFile | None]:
    """Why a scan's prediction is wrong, or its deflated entry (None once `failed` is set)."""
    try:
        num_points = scan_num_points(entry.scan_path, record=KITTI_RECORD)
    except ScanFormatError as exc:
        return str(exc), None
    pred = entry.prediction_in(predictions)
    if not pred.is_file():
        return f"{pred} is missing (no prediction for test scan {entry.key})", None
    data = pred.read_bytes()
    problem = _label_problem(data, str(pred), num_points, valid)
    if problem or failed.is_set():
        return problem, None
    return None, deflate_file(_entry_name(entry), data)


def write_submission(
    predictions: Path | str,
    dataset: Path | str,
    out: Path | str,
    allow_partial: bool = False,
    description: str | None = None,
    *,
    labels: LabelConfig,
    progress: bool = False,
    workers: int | None = None,
    things: Sequence[int] | None = None,
) -> SubmissionCheck:
    """Build the submission zip of a predictions tree for the test scans of `dataset` (with
    `things`, a panoptic one, validated as such).

    `description` is the text of `description.txt` (`rangeret.submission.leaderboard.description_text`);
    without it the file holds the leaderboard's three lines with the benchmark's defaults.
    Raises `SubmissionError` listing every missing or wrong prediction (and an incomplete local
    test set unless `allow_partial`); in that case no file is written. The archive is validated
    before it is moved into place, and is byte-for-byte reproducible for the same inputs whatever
    the number of `workers`, the threads that read, check and deflate the predictions ahead
    (default: every CPU this process may use).
    """
    predictions, dataset, out = Path(predictions), Path(dataset), Path(out)
    if description is None:
        description = "\n".join(LeaderboardEntry().lines())
    if out.suffix != ".zip":
        raise SubmissionError([f"{out}: the archive's name must end with .zip"])
    scans, _, problems = _dataset_scans(dataset, allow_partial)
    if not scans and not problems:
        problems.append(f"{dataset} holds no test scan (sequences 11 to 21)")
    valid = _valid_id_table(labels)
    # Once a problem is found nothing more is written, so the workers stop deflating.
    failed = threading.Event()
    if problems:
        failed.set()

    def read(entry: ScanEntry) -> tuple[str | None, DeflatedFile | None]:
        return _read_prediction(entry, predictions, valid, failed)

    with atomic_path(out, suffix=".zip") as tmp:
        with ReproducibleZip(tmp) as zf:
            for name in required_directories():
                zf.add_directory(name)
            outcomes = map_ahead(read, scans, workers)
            for problem, file in tqdm(
                outcomes, total=len(scans), desc="submission", unit="scan", disable=not progress
            ):
                if problem:
                    problems.append(problem)
                    failed.set()
                elif file is not None and not problems:
                    zf.add_deflated(file)
            if description and not problems:
                zf.add_file(DESCRIPTION_NAME, description.rstrip("\n") + "\n")
        if problems:
            raise SubmissionError(problems)
        check = validate_submission(
            tmp, dataset, allow_partial=allow_partial, labels=labels, things=things
        )
        check.path = out
        check.raise_for_problems()
    return check


def validate_submission(
    archive: Path | str,
    dataset: Path | str,
    allow_partial: bool = False,
    *,
    labels: LabelConfig,
    progress: bool = False,
    things: Sequence[int] | None = None,
) -> SubmissionCheck:
    """Check a submission zip against the dataset's test scans and the official test split.

    Checks what the official validator checks (directory entries, one prediction per scan with
    one label per point) and more: raw ids the learning map can produce, unsafe or unexpected
    entries, duplicates, and, unless `allow_partial`, that the dataset is the full test split.
    A `description.txt` without the leaderboard's three lines is a warning: the server accepts it
    but shows the method as Anonymous. With `things` (the thing classes: a panoptic archive),
    labels whose thing points never carry an instance are refused as semantic ones.
    """
    archive, dataset = Path(archive), Path(dataset)
    check = SubmissionCheck(path=archive, partial=allow_partial)
    if archive.suffix != ".zip":
        check.problems.append(f"{archive}: the archive's name must end with .zip")
    if not archive.is_file():
        check.problems.append(f"{archive} does not exist")
        return check
    scans, present, dataset_problems = _dataset_scans(dataset, allow_partial)
    check.sequences = present
    check.problems += dataset_problems
    valid = _valid_id_table(labels)
    counts = [0, 0]
    thing_ids = np.zeros(1 << 16, dtype=bool)
    for raw, cls in labels.raw_to_class.items():
        thing_ids[raw] = things is not None and cls in things
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as exc:
        check.problems.append(f"{archive} is not a readable zip archive ({exc})")
        return check
    with zf:
        infos = zf.infolist()
        names = [i.filename for i in infos]
        entries: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            problem = unsafe_entry(info)
            if problem:
                check.problems.append(f"{archive}: entry {info.filename!r} {problem}")
            elif info.filename in entries:
                check.problems.append(f"{archive}: entry {info.filename!r} appears more than once")
            entries[info.filename] = info
        directories = {n for n in names if n.endswith("/")}
        for name in required_directories():
            if name not in directories:
                check.problems.append(f"{archive}: directory entry {name!r} is missing")
        allowed_dirs = set(required_directories())
        wanted = {_entry_name(e): e for e in scans}
        for name in names:
            if name in allowed_dirs or name == DESCRIPTION_NAME or name in wanted:
                continue
            match = _LABEL_ENTRY.match(name)
            if match and match.group(1) in TEST_SCAN_COUNTS and allow_partial:
                continue  # a prediction for a scan this partial local copy lacks
            if match and match.group(1) in TEST_SCAN_COUNTS:
                check.problems.append(f"{archive}: {name} has no matching test scan in {dataset}")
            else:
                check.problems.append(f"{archive}: unexpected entry {name!r}")
        check.warnings += description_warnings(zf, entries.get(DESCRIPTION_NAME), archive)
        for name, entry in tqdm(wanted.items(), desc="validate", unit="scan", disable=not progress):
            try:
                num_points = scan_num_points(entry.scan_path, record=KITTI_RECORD)
            except ScanFormatError as exc:
                check.problems.append(str(exc))
                continue
            info = entries.get(name)
            if info is None:
                check.problems.append(f"{archive}: {name} is missing (test scan {entry.key})")
                continue
            if info.file_size != num_points * LABEL_BYTES:
                check.problems.append(
                    f"{archive}: {name} holds {info.file_size / LABEL_BYTES:g} labels but "
                    f"scan {entry.key} has {num_points} points"
                )
                continue
            try:
                data = zf.read(info)
            except (zipfile.BadZipFile, OSError, ValueError) as exc:
                check.problems.append(f"{archive}: {name} cannot be read ({exc})")
                continue
            problem = _label_problem(data, f"{archive}: {name}", num_points, valid)
            if problem:
                check.problems.append(problem)
            elif things is not None:
                _count_objects(data, thing_ids, counts)
            check.scans += 1
    refusal = None if things is None else instance_problem(archive, counts)
    if refusal is not None:
        check.problems.append(refusal)
    return check


#: The most bytes of description.txt read (the leaderboard's four fields take a few hundred).
MAX_DESCRIPTION_BYTES = 64 << 10


def description_warnings(
    zf: zipfile.ZipFile, info: zipfile.ZipInfo | None, archive: Path
) -> list[str]:
    """What keeps the leaderboard from showing the archive's name and links, or []."""
    if info is None:
        return [
            f"{archive} has no {DESCRIPTION_NAME}: the leaderboard shows the method as "
            f"{DEFAULT_NAME} with {DEFAULT_URL} links (rangeret submission --method-name, "
            "--pdf-url and --code-url write it)"
        ]
    if info.file_size > MAX_DESCRIPTION_BYTES:
        return [
            f"{archive}: {DESCRIPTION_NAME} is {info.file_size:,} bytes, more than the "
            f"{MAX_DESCRIPTION_BYTES:,} read of it: the leaderboard shows none of it"
        ]
    try:
        text = zf.read(info).decode("utf-8")
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        return [f"{archive}: {DESCRIPTION_NAME} cannot be read as UTF-8 text ({exc})"]
    return [f"{archive}: {DESCRIPTION_NAME} {p}" for p in description_problems(text)]


def unsafe_entry(info: zipfile.ZipInfo) -> str | None:
    """Why an entry could escape the extraction folder or is not a plain file or folder."""
    name = info.filename
    if name.startswith("/") or "\\" in name or re.match(r"^[A-Za-z]:", name):
        return "has an absolute or Windows path"
    if ".." in name.split("/"):
        return "contains '..' and would escape the extraction folder"
    kind = stat.S_IFMT(info.external_attr >> 16)
    if kind and kind not in (stat.S_IFREG, stat.S_IFDIR):
        return "is a link or special file, not a plain file or folder"
    return None
