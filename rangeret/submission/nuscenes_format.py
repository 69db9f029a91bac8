"""What a nuScenes results folder holds: its format per challenge (`ResultsFormat`:
nuScenes-lidarseg's `.bin` files, nuScenes-panoptic's `.npz` files), submission.json's meta,
and the checks of one prediction file's values, shared by the archive writer and validator
(`rangeret.submission.nuscenes`).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from rangeret.dataset.layout import ScanEntry
from rangeret.io.panoptic_labels import PANOPTIC_NPZ, THOUSANDS
from rangeret.io.scans import ScanFormatError
from rangeret.submission.leaderboard import LeaderboardEntry

#: The keys of submission.json's "meta", each a boolean.
META_KEYS = ("use_camera", "use_lidar", "use_radar", "use_map", "use_external")
#: The task a nuScenes-panoptic submission.json names (the other, tracking, is not written here).
PANOPTIC_TASK = "segmentation"


#: Bytes an `.npz` of one array may add to the array's own (zip and npy headers).
NPZ_HEADROOM = 64 << 10
#: The most bytes `submission.json` may take (the devkit's is about 200).
MAX_META_BYTES = 64 << 10


@dataclass(frozen=True)
class ResultsFormat:
    """What one nuScenes challenge's results folder holds per keyframe, and its meta's extras."""

    #: The folder of the prediction files (`<folder>/<split>/`), as the layout writes it.
    folder: str
    #: What each file's name ends with after its sample_data token.
    suffix: str
    #: How messages name the challenge.
    title: str
    #: Keys of "meta" beyond the five flags, with the one value each must have.
    meta_extra: tuple[tuple[str, str], ...] = ()
    #: Whether the files are the panoptic ones (the layout's `panoptic` discovery).
    panoptic: bool = False

    def entry_name(self, split: str, entry: ScanEntry) -> str:
        """The archive member of a keyframe's prediction."""
        return f"{self.folder}/{split}/{entry.name}{self.suffix}"

    def meta_keys(self) -> tuple[str, ...]:
        """Every key "meta" must hold."""
        return (*(k for k, _ in self.meta_extra), *META_KEYS)

    def most_bytes(self, num_points: int) -> int:
        """The most bytes a prediction of `num_points` points may take: one byte a point in a
        `.bin`; two a point, plus an npz's headers, in a panoptic `.npz` (compressed or not)."""
        return 2 * num_points + NPZ_HEADROOM if self.panoptic else num_points


LIDARSEG_RESULTS = ResultsFormat("lidarseg", "_lidarseg.bin", "nuScenes-lidarseg")
PANOPTIC_RESULTS = ResultsFormat(
    "panoptic",
    "_panoptic.npz",
    "nuScenes-panoptic",
    meta_extra=(("task", PANOPTIC_TASK),),
    panoptic=True,
)


@dataclass(frozen=True)
class SubmissionMeta:
    """The modalities and data a method used, as submission.json declares them."""

    use_camera: bool = False
    use_lidar: bool = True
    use_radar: bool = False
    use_map: bool = False
    use_external: bool = False

    def to_dict(self, results: ResultsFormat | None = None) -> dict[str, bool | str]:
        """The "meta" object (with the `results` format's extra keys first)."""
        extra = dict(results.meta_extra) if results is not None else {}
        return {**extra, **{key: bool(getattr(self, key)) for key in META_KEYS}}


def submission_json(
    meta: SubmissionMeta,
    entry: LeaderboardEntry,
    checkpoint_sha256: str | None,
    results: ResultsFormat = LIDARSEG_RESULTS,
) -> str:
    """The text of `<split>/submission.json`: the meta flags, and the method beside them."""
    method = {
        "name": entry.name,
        "pdf_url": entry.pdf_url,
        "code_url": entry.code_url,
        "checkpoint_sha256": checkpoint_sha256 or "unknown",
    }
    return json.dumps({"meta": meta.to_dict(results), "method": method}, indent=2) + "\n"


def _classes(
    data: bytes, name: str, num_points: int, results: ResultsFormat
) -> tuple[np.ndarray | None, np.ndarray | None, str | None]:
    """A prediction file's classes and (panoptic) instances, or why it is not what the devkit
    takes."""
    if results.panoptic:
        try:
            values = PANOPTIC_NPZ.parse(data, name, num_points)
        except ScanFormatError as exc:
            return None, None, str(exc)
        return THOUSANDS.semantic(values), THOUSANDS.instance(values), None
    if len(data) != num_points:
        return (
            None,
            None,
            f"{name} holds {len(data)} predictions but its point cloud has {num_points} points",
        )
    return np.frombuffer(data, dtype=np.uint8), None, None


def values_problem(
    data: bytes,
    name: str,
    num_points: int,
    num_classes: int,
    results: ResultsFormat = LIDARSEG_RESULTS,
    things: Sequence[int] = (),
    counts: list[int] | None = None,
) -> str | None:
    """Why a prediction's bytes are not what the devkit takes, or None; with `counts`, adds the
    file's thing points and those of them with an object to it."""
    values, instances, problem = _classes(data, name, num_points, results)
    if problem is not None or values is None:
        return problem
    bad = np.flatnonzero((values < 1) | (values >= num_classes))
    of = "with a class " if results.panoptic else ""
    if bad.size:
        return (
            f"{name} holds {bad.size} value(s) {of}outside 1..{num_classes - 1}, the first "
            f"{of and 'class '}{int(values[bad[0]])} at point {int(bad[0])} (0 is ignore, which "
            "is not predicted)"
        )
    if instances is not None and counts is not None:
        thing = np.isin(values, np.asarray(things, dtype=values.dtype))
        counts[0] += int(thing.sum())
        counts[1] += int((thing & (instances > 0)).sum())
    return None


def required_directories(split: str, results: ResultsFormat = LIDARSEG_RESULTS) -> Iterator[str]:
    """The folders of the results folder, in order."""
    yield f"{results.folder}/"
    yield f"{results.folder}/{split}/"
    yield f"{split}/"


def meta_problems(data: object, name: str, results: ResultsFormat = LIDARSEG_RESULTS) -> list[str]:
    """What the devkit refuses in submission.json's content (`name` names the file)."""
    if not isinstance(data, Mapping) or not isinstance(data.get("meta"), Mapping):
        return [f'{name} must hold an object with a "meta" object']
    meta = data["meta"]
    keys = set(meta)
    wanted = results.meta_keys()
    if keys != set(wanted):
        missing = [k for k in wanted if k not in keys]
        extra = sorted(str(k) for k in keys - set(wanted))
        said = "; ".join(
            part
            for part in (
                f"missing {', '.join(missing)}" if missing else "",
                f"unknown {', '.join(extra)}" if extra else "",
            )
            if part
        )
        return [f"{name}: meta must hold exactly {', '.join(wanted)} ({said})"]
    wrong = [
        f"{name}: meta.{key} must be {json.dumps(value)}, got {json.dumps(meta[key])}"
        for key, value in results.meta_extra
        if meta[key] != value
    ]
    return wrong + [
        f"{name}: meta.{key} must be true or false, got {json.dumps(meta[key])}"
        for key in META_KEYS
        if type(meta[key]) is not bool
    ]
