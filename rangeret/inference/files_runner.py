"""Labelling point-cloud files one at a time: every runner of single files (`rangeret predict
--files`) reads, labels and writes each file the same way.

Each file is read by its format (`rangeret.io.point_files`), filled into the profile's point
record (`to_record`), labelled (`label_cloud`, the path every runner shares) and written as
`OUT/<stem>.label`, with `<stem>.npy` confidences and a labelled copy in its own format when
asked. With panoptic segmentation the `.label` file holds the benchmark's panoptic labels, and a
labelled copy's `label` the raw ids (`field_labels`) with each point's object in `instance`. A
file that cannot be read or labelled is a named failure; the others still run.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from rangeret.exceptions import MissingExtraError, RangeRetError
from rangeret.inference.clouds import label_cloud
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import RunSummary, ScanPrediction
from rangeret.inference.timing import StageTimes
from rangeret.io.decode_limits import DEFAULT_LIMITS, DecodeLimits
from rangeret.io.point_fields import to_record
from rangeret.io.point_files import read_point_file, write_labelled
from rangeret.io.scans import write_confidence, write_labels


def field_labels(predictor: Predictor, found: ScanPrediction) -> np.ndarray:
    """What a `label` field beside the points holds (a labelled copy's, a labelled bag's, the
    ROS 2 node's): the raw ids a run without panoptic segmentation writes, which with it are
    the semantic part of the panoptic labels (the objects go in an `instance` field)."""
    if found.instances is None:
        return found.labels
    return predictor.profile.layout.panoptic_encoding.semantic(found.labels)


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
    limits: DecodeLimits = DEFAULT_LIMITS,
) -> dict[str, Any]:
    """Label one file into `out` (read within `limits`); what run.json records of it. Bad input
    raises the RangeRetError naming the file."""
    profile = predictor.profile
    times = times if times is not None else StageTimes()
    with times.stage("read"):
        point_file = read_point_file(path, record=profile.points, limits=limits)
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
            labels = field_labels(predictor, found)
            write_labelled(target, point_file, labels, found.confidence, found.instances)
            written["labelled"] = str(target)
    info = point_file.describe()
    objects = {} if found.instances is None else {"instances": found.num_instances}
    return {"file": str(path), **info, **cloud.describe(), **objects, "outputs": written}


def _problem(exc: Exception, path: Path) -> str:
    """An error's message without the leading file name the report puts before it."""
    text = str(exc)
    return text.removeprefix(f"{path}: ")


def label_files(
    predictor: Predictor,
    files: Sequence[Path],
    out: Path,
    *,
    overrides: Mapping[str, str],
    save_confidence: bool,
    labelled: bool,
    progress: bool = True,
    limits: DecodeLimits = DEFAULT_LIMITS,
) -> tuple[RunSummary, list[dict[str, Any]]]:
    """Label every file into `out`, each read within `limits`: the run's summary and, per file,
    what run.json records of it (or its error). A missing extra stops the run: no file of that
    format could be read."""
    out.mkdir(parents=True, exist_ok=True)
    summary = RunSummary(total=len(files))
    inputs: list[dict[str, Any]] = []
    start = time.perf_counter()
    for path in tqdm(files, desc="predict", unit="file", disable=not progress):
        try:
            entry = predict_file(
                predictor,
                path,
                out,
                overrides=overrides,
                save_confidence=save_confidence,
                labelled=labelled,
                times=summary.times,
                limits=limits,
            )
        except MissingExtraError:
            raise
        except RangeRetError as exc:
            summary.add(str(path), _problem(exc, path))
            inputs.append({"file": str(path), "error": _problem(exc, path)})
            continue
        summary.add(str(path), None, entry["points"])
        inputs.append(entry)
    summary.seconds = time.perf_counter() - start
    return summary, inputs
