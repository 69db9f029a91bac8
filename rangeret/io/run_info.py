"""`run.json`: how a predictions tree was made, written beside it by every runner the same way.

It records the network (model, checkpoint and its SHA-256, whether these are the demo weights,
projection, kNN, test-time augmentation, device), the data (dataset, sequences), the batch size,
the runner and the start time, so that any tree can be traced back to what produced it. An
output that is not a tree (a labelled bag) gets the same record at an explicit path
(`write_run_record`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rangeret.exceptions import InputError
from rangeret.io.atomic import atomic_write_text

RUN_INFO = "run.json"


class RunInfoError(InputError, ValueError):
    """A run record (run.json) that cannot be read."""


def write_run_info(
    out: Path | str,
    network: Mapping[str, Any],
    *,
    runner: str,
    dataset: Path | str | None,
    sequences: Sequence[str],
    batch_size: int,
    inputs: Sequence[Mapping[str, Any]] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write `OUT/run.json` atomically and return its path.

    `network` is the description of the network and its options (`Predictor.describe()`, or
    `describe_network` where no predictor is loaded in this process). `dataset` is None for runs
    on single files; `inputs` describes each file read (format, points, how its fields filled the
    record) and `extra` adds run-wide keys.
    """
    details: dict[str, Any] = {
        "batch_size": batch_size,
        "dataset": None if dataset is None else str(dataset),
        "sequences": list(sequences),
        **(extra or {}),
    }
    if inputs is not None:
        details["inputs"] = [dict(i) for i in inputs]
    return write_run_record(Path(out) / RUN_INFO, network, runner=runner, details=details)


def write_run_record(
    path: Path | str,
    network: Mapping[str, Any],
    *,
    runner: str,
    details: Mapping[str, Any],
    started: str | None = None,
) -> Path:
    """Write a run record at the explicit `path` atomically (for outputs that are not a tree,
    such as a labelled bag's `OUT.run.json`): the network, `details` (what the run read and
    wrote), the runner and its start time (`started`, else now)."""
    record = {
        **network,
        **details,
        "runner": runner,
        "started": started or started_now(),
    }
    path = Path(path)
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    return path


def started_now() -> str:
    """The current local time as run records write it."""
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def read_run_info(out: Path | str) -> dict[str, Any]:
    """`OUT/run.json` as a dict, or {} when the tree has none; a file that is not a JSON object
    is a ValueError naming it."""
    path = Path(out) / RUN_INFO
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise RunInfoError(f"{path} is not a readable run record ({exc})") from exc
    if not isinstance(record, dict):
        raise RunInfoError(f"{path} is not a run record (a JSON object)")
    return record
