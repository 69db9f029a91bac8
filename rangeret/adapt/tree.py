"""A labelled dataset resampled to another sensor, scan by scan, into a tree in the target's
layout, with `OUT/adapt.json` recording how.

The work is three steps that any driver shares (the command line runs them in one process; a
Ray job can hand the jobs of step 2 to its workers):

1. `plan_adaptation` checks the profiles and the output folder, lists the chosen scans with their
   outputs, marks those an earlier run with the same settings finished, and records the settings
   in `OUT/adapt.json` before anything else is written;
2. `adapt_one` reads one scan and its labels, adapts them (`adapt_scan`) and writes them;
3. `finish` writes `OUT/adapt.json` with the counts of the scans adapted, and `summary` says
   what was adapted, dropped and left empty, for the driver to print.

An output folder that is, holds or lies inside the dataset is refused, so no input is ever
replaced; settings other than those `adapt.json` records need `overwrite`.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from rangeret.adapt.resample import (
    AdaptError,
    AdaptStats,
    adapt_scan,
    check_offset,
    check_profiles,
    unmeasured_beams,
)
from rangeret.dataset.beams import beam_elevations
from rangeret.dataset.label_map import LabelMap
from rangeret.dataset.layout import (
    DatasetLayoutError,
    ScanEntry,
    SequenceLayout,
    discover,
    labels_dir,
    velodyne_dir,
)
from rangeret.dataset.profiles import DatasetProfile
from rangeret.io.output_paths import landing_inside
from rangeret.io.run_info import read_record, started_now, write_run_record
from rangeret.io.scans import ScanFormatError, read_scan, scan_num_points, write_scan

#: The record of an adapted tree, in its root.
ADAPT_INFO = "adapt.json"
RUNNER = "rangeret adapt"
#: The keys of adapt.json that must match for a run to resume into the tree.
SETTINGS = ("dataset", "source_profile", "target_profile", "sensor_offset", "label_map")


@dataclass(frozen=True)
class AdaptSettings:
    """What every scan of a run is adapted with: the profiles, the target sensor's position in
    the source's frame (m) and the label map (None: raw ids kept)."""

    source: DatasetProfile
    target: DatasetProfile
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    label_map: LabelMap | None = None

    def record(self, dataset: Path) -> dict[str, Any]:
        """The settings as adapt.json records them (plain JSON data)."""
        return {
            "dataset": str(dataset),
            "source_profile": _profile_record(self.source),
            "target_profile": _profile_record(self.target),
            "sensor_offset": list(self.offset),
            "label_map": None if self.label_map is None else self.label_map.to_dict(),
        }


@dataclass(frozen=True)
class ScanJob:
    """One scan to adapt: its source entry and where its adapted scan and labels go; `done` when
    an earlier run with the same settings wrote both."""

    entry: ScanEntry
    scan_out: Path
    label_out: Path
    done: bool = False


@dataclass
class AdaptPlan:
    """A run's dataset, output tree, settings and scans, as `plan_adaptation` found them."""

    dataset: Path
    out: Path
    sequences: list[str]
    settings: AdaptSettings
    jobs: list[ScanJob]
    overwrite: bool = False
    started: str = field(default_factory=started_now)

    @property
    def todo(self) -> list[ScanJob]:
        """The scans this run adapts (those not done)."""
        return [job for job in self.jobs if not job.done]

    @property
    def skipped(self) -> int:
        """Scans an earlier run with the same settings finished."""
        return sum(job.done for job in self.jobs)


def plan_adaptation(
    dataset: Path | str,
    out: Path | str,
    sequences: Sequence[str],
    settings: AdaptSettings,
    *,
    overwrite: bool = False,
) -> AdaptPlan:
    """The scans of `sequences` (each with its labels) and their outputs in the target's layout,
    after checking the profiles, that `out` neither is, holds nor lies inside `dataset`, and that
    its adapt.json was written with these settings (else `overwrite` is needed); records the
    settings in `out/adapt.json` before any scan is written."""
    source, target = settings.source, settings.target
    check_profiles(source, target)
    check_offset(settings.offset)
    dataset, out = Path(dataset), Path(out)
    _check_apart(dataset, out)
    found = discover(dataset, sequences, with_labels=True, layout=source.layout)
    if found.problems:
        raise DatasetLayoutError("; ".join(found.problems))
    record = settings.record(Path(os.path.realpath(dataset)))
    previous = read_adapt_info(out)
    differ = [k for k in SETTINGS if previous and _setting(previous, k) != _setting(record, k)]
    layout = cast(SequenceLayout, target.layout)
    jobs = []
    for entry in found.scans:
        sequence = layout.normalise(entry.sequence)
        scan_out = velodyne_dir(out, sequence, layout=layout) / f"{entry.name}.bin"
        label_out = labels_dir(out, sequence, layout=layout) / f"{entry.name}.label"
        jobs.append(ScanJob(entry, scan_out, label_out, _finished(scan_out, label_out, target)))
    if not overwrite and _holds_scans(out, layout):
        if differ:
            raise AdaptError(
                f"{out / ADAPT_INFO} records another {', '.join(differ)} than this run's; pass "
                "--overwrite to adapt into it anyway, or choose another output folder"
            )
        if not previous:
            raise AdaptError(
                f"{out} holds adapted scans but no {ADAPT_INFO} saying how they were made; pass "
                "--overwrite to adapt into it anyway, or choose another output folder"
            )
    outputs = [out / ADAPT_INFO, *(path for j in jobs for path in (j.scan_out, j.label_out))]
    landed = landing_inside(outputs, dataset)
    if landed is not None:
        raise AdaptError(
            f"{landed[0]} leads to {landed[1]}, inside the dataset {dataset}; write the adapted "
            "dataset elsewhere (inputs are never replaced, --overwrite or not)"
        )
    if overwrite or differ:
        jobs = [ScanJob(j.entry, j.scan_out, j.label_out) for j in jobs]
    plan = AdaptPlan(dataset, out, list(sequences), settings, jobs, overwrite)
    _write_info(plan, None)
    return plan


def adapt_one(job: ScanJob, settings: AdaptSettings) -> AdaptStats:
    """Read one scan and its labels, adapt them and write them to the job's outputs (nothing
    where no point is kept: `empty_scans` counts it); the scan's counts."""
    source, target = settings.source, settings.target
    entry = job.entry
    points = read_scan(entry.scan_path, source.points)
    if entry.label_path is None:
        raise AdaptError(f"scan {entry.key} has no labels")
    labels = entry.label_file.read(entry.label_path, len(points))
    adapted, raw, stats = adapt_scan(
        points, labels, source, target, settings.offset, settings.label_map, scan=entry.key
    )
    if not len(adapted):
        # No reader takes an empty scan: the tree leaves it out (an earlier run's is removed).
        job.scan_out.unlink(missing_ok=True)
        job.label_out.unlink(missing_ok=True)
        return stats
    target.layout.label_file.write(job.label_out, raw)
    write_scan(job.scan_out, adapted, record=target.points)
    return stats


def finish(plan: AdaptPlan, results: Iterable[AdaptStats]) -> Path:
    """Write `OUT/adapt.json` with the settings and the summed counts of the scans adapted by
    this run (`scans.skipped`: those an earlier run finished); its path."""
    total = sum(results, AdaptStats())
    return _write_info(plan, total)


def summary(plan: AdaptPlan, results: Iterable[AdaptStats], record: Path) -> str:
    """What the run adapted, dropped and left empty, the target's beams no source point can
    reach, and `record` (the `OUT/adapt.json` that `finish` wrote), in lines."""
    total = sum(results, AdaptStats())
    skipped = f" ({plan.skipped} already there)" if plan.skipped else ""
    lines = [f"scans adapted into {plan.out}: {total.scans}{skipped}"]
    if total.scans:
        lines.append(
            f"points: {total.points_kept:,} of {total.points_in:,} kept; dropped "
            f"{total.dropped_fov:,} outside the field of view, {total.dropped_range:,} out of "
            f"range, {total.dropped_collisions:,} on a pixel another point won"
        )
    if total.empty_scans:
        lines.append(f"{total.empty_scans} scan(s) kept no point and were left out")
    source, target = plan.settings.source, plan.settings.target
    beams = unmeasured_beams(source, target)
    if beams:
        lines.append(
            f"{len(beams)} beam(s) of {target.name} lie outside the source's field of view and "
            f"stay empty: {', '.join(map(str, beams))}"
        )
    lines.append(f"record: {record}")
    return "\n".join(lines)


def read_adapt_info(out: Path | str) -> dict[str, Any]:
    """`OUT/adapt.json` as a dict, or {} where there is none; a file that is not a JSON object
    is a `RunInfoError` naming it."""
    return read_record(Path(out) / ADAPT_INFO, "adapt record")


def _profile_record(profile: DatasetProfile) -> dict[str, Any]:
    """A profile's name and the SHA-256 of its YAML form, so another profile of one name shows."""
    import hashlib

    text = profile.to_yaml().encode("utf-8")
    return {"name": profile.name, "sha256": hashlib.sha256(text).hexdigest()}


def _setting(record: dict[str, Any], key: str) -> Any:
    """One setting as compared between runs (a label map by its mapping, not its path)."""
    value = record.get(key)
    if key == "label_map" and isinstance(value, dict):
        return value.get("mapping")
    return value


def _check_apart(dataset: Path, out: Path) -> None:
    """An `AdaptError` when `out` is, holds or lies inside `dataset` (once links are resolved)."""
    root, target = os.path.realpath(dataset), os.path.realpath(out)
    if os.path.commonpath([root, target]) in (root, target):
        raise AdaptError(
            f"the output folder {out} is, holds or lies inside the dataset {dataset}; write the "
            "adapted dataset elsewhere (inputs are never replaced, --overwrite or not)"
        )


def _holds_scans(out: Path, layout: SequenceLayout) -> bool:
    """Whether the tree `out` holds any scan in the target's layout."""
    base = layout.sequences_root(out)
    scans = base.glob("*/velodyne/*.bin") if base.is_dir() else ()
    return any(not scan.name.startswith(".") for scan in scans)


def _finished(scan_out: Path, label_out: Path, target: DatasetProfile) -> bool:
    """Whether an adapted scan and its labels are both there, one label per point."""
    try:
        points = scan_num_points(scan_out, record=target.points)
        return target.layout.label_file.count(label_out) == points
    except (OSError, ScanFormatError):
        return False


def _write_info(plan: AdaptPlan, total: AdaptStats | None) -> Path:
    """Write adapt.json: the settings, and the counts once the run has finished (None: running)."""
    settings = plan.settings
    target = settings.target
    details = {
        **settings.record(Path(os.path.realpath(plan.dataset))),
        "out": str(plan.out),
        "sequences": plan.sequences,
        "status": "running" if total is None else "finished",
        "scans": {
            "chosen": len(plan.jobs),
            "adapted": None if total is None else total.scans,
            "skipped": plan.skipped,
        },
        "counts": None if total is None else total.to_dict(),
        "unmeasured_beams": unmeasured_beams(settings.source, target),
        "target_beam_elevations": [round(a, 6) for a in beam_elevations(target).tolist()],
        "overwrite": plan.overwrite,
    }
    path = plan.out / ADAPT_INFO
    plan.out.mkdir(parents=True, exist_ok=True)
    return write_run_record(path, {}, runner=RUNNER, details=details, started=plan.started)
