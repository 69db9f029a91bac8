"""`run.json`: how a predictions tree was made, written beside it by every runner the same way.

It records the network (model, checkpoint and its SHA-256, whether these are the demo weights,
the checkpoint they were fine-tuned from, projection, kNN, test-time augmentation, device,
precision, and why that precision where the network ran in the writing process), the data
(dataset, sequences), the batch size, the runner and the start time, so that any tree can be
traced back to what produced it. Its top-level keys describe the latest run into the tree;
`runs` lists every run that wrote into it, oldest first (a record written before runs were
listed becomes the first entry). A run with other weights than those whose predictions the tree
holds is refused unless it overwrites. An output that is not a tree (a labelled bag) gets one
run's record at an explicit path (`write_run_record`).
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

#: What each entry of `runs` keeps of its run: what it predicted, with which weights and how.
RUN_KEYS = (
    "runner",
    "started",
    "dataset",
    "sequences",
    "files",
    "model",
    "checkpoint",
    "checkpoint_sha256",
    "demo_weights",
    "parent",
    "profile",
    "network_profile",
    "label_map",
    "precision",
    "precision_reason",
    "backend",
    "device",
    "batch_size",
    "overwrite",
    "panoptic",
)


class RunInfoError(InputError, ValueError):
    """A run record (run.json) that cannot be read."""


class WeightsMismatchError(InputError, ValueError):
    """A run with other weights than those whose predictions the tree already holds."""


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
    overwrite: bool = False,
    started: str | None = None,
) -> Path:
    """Add this run to `OUT/run.json` (read, merged and written atomically) and return its path.

    `network` is the description of the network and its options (`Predictor.describe()`, or
    `describe_network` where no predictor is loaded in this process). `dataset` is None for runs
    on single files; `inputs` describes each file read (format, points, how its fields filled the
    record) and `extra` adds run-wide keys. The top-level keys become this run's and `runs` gains
    its entry; other weights than the tree's are a `WeightsMismatchError` unless `overwrite`
    (`check_weights`).
    """
    out = Path(out)
    previous = check_weights(
        out,
        network.get("checkpoint_sha256"),
        overwrite=overwrite,
        panoptic=bool(network.get("panoptic")),
    )
    details: dict[str, Any] = {
        "batch_size": batch_size,
        "dataset": None if dataset is None else str(dataset),
        "sequences": list(sequences),
        **(extra or {}),
        "overwrite": overwrite,
    }
    if inputs is not None:
        details["inputs"] = [dict(i) for i in inputs]
        details["files"] = [str(i.get("file")) for i in inputs]
    record = run_record(network, runner=runner, details=details, started=started)
    record["runs"] = [*recorded_runs(previous, out / RUN_INFO), run_entry(record)]
    path = out / RUN_INFO
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    return path


def check_weights(
    out: Path | str, sha256: str | None, *, overwrite: bool = False, panoptic: bool = False
) -> dict[str, Any]:
    """The tree's run record, after checking that the runs in it used the weights of `sha256`
    and the same task (`panoptic` or semantic: a panoptic run must not take a semantic
    prediction for its own); a run recorded otherwise is a `WeightsMismatchError` naming the
    difference and the tree, unless `overwrite` (mixing is then allowed). Called before anything
    is written."""
    record = read_run_info(out)
    if overwrite or not record:
        return record
    runs = recorded_runs(record, Path(out) / RUN_INFO)
    tasks = {bool(run.get("panoptic")) for run in runs}
    if tasks - {panoptic}:
        have, this = ("semantic", "panoptic") if panoptic else ("panoptic", "semantic")
        raise WeightsMismatchError(
            f"{out} holds {have} predictions and this run is {this}; write to another folder, "
            "or pass --overwrite to predict into it anyway"
        )
    if sha256 is None:
        return record
    others = sorted(
        {
            str(run["checkpoint_sha256"])
            for run in runs
            if run.get("checkpoint_sha256") not in (None, sha256)
        }
    )
    if others:
        theirs = ", ".join(h[:12] for h in others)
        raise WeightsMismatchError(
            f"{out} holds predictions from other weights (checkpoint sha256 {theirs}) than "
            f"this run's ({sha256[:12]}); write to another folder, or pass --overwrite to "
            "predict into it anyway"
        )
    return record


def recorded_runs(record: Mapping[str, Any], path: Path) -> list[dict[str, Any]]:
    """The runs a record lists, oldest first: its `runs`, or for a record written before runs
    were listed, the one run its top-level keys describe ([] for no record)."""
    if not record:
        return []
    if "runs" not in record:
        return [run_entry(record)]
    runs = record["runs"]
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise RunInfoError(f"{path}: `runs` is not a list of run records")
    return [dict(r) for r in runs]


def run_entry(record: Mapping[str, Any]) -> dict[str, Any]:
    """The entry of `runs` for one run's record: the keys of `RUN_KEYS` it has."""
    return {key: record[key] for key in RUN_KEYS if key in record}


def write_run_record(
    path: Path | str,
    network: Mapping[str, Any],
    *,
    runner: str,
    details: Mapping[str, Any],
    started: str | None = None,
) -> Path:
    """Write one run's record at the explicit `path` atomically (for outputs that are not a
    tree, such as a labelled bag's `OUT.run.json`, which its run replaces whole)."""
    record = run_record(network, runner=runner, details=details, started=started)
    path = Path(path)
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    return path


def run_record(
    network: Mapping[str, Any],
    *,
    runner: str,
    details: Mapping[str, Any],
    started: str | None = None,
) -> dict[str, Any]:
    """One run's record: the network (with why it ran at its precision, where this process
    chose it), `details` (what the run read and wrote), the runner and its start time
    (`started`, else now)."""
    return {
        **network,
        **precision_reason(network),
        **details,
        "runner": runner,
        "started": started or started_now(),
    }


def precision_reason(network: Mapping[str, Any]) -> dict[str, str]:
    """`{"precision_reason": why}` for a network whose precision this process resolved as it
    loaded it (`rangeret.inference.runtime.precision.resolved_reason`), else {}: a record written
    where the network runs elsewhere says only what was asked for."""
    from rangeret.inference.runtime.precision import resolved_reason

    precision, device = network.get("precision"), network.get("device")
    if "precision_reason" in network or not precision or not device:
        return {}
    reason = resolved_reason(str(precision), str(device), str(network.get("backend", "torch")))
    return {} if reason is None else {"precision_reason": reason}


def started_now() -> str:
    """The current local time as run records write it."""
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def read_run_info(out: Path | str) -> dict[str, Any]:
    """`OUT/run.json` as a dict, or {} when the tree has none; a file that is not a JSON object
    is a ValueError naming it."""
    return read_record(Path(out) / RUN_INFO, "run record")


def read_record(path: Path, kind: str) -> dict[str, Any]:
    """A JSON record file (a run's, an adaptation's) as a dict, or {} where there is none; a file
    that is not a JSON object is a `RunInfoError` naming it and its `kind`."""
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except RecursionError as exc:
        raise RunInfoError(f"{path} is not a readable {kind} (it nests too deeply)") from exc
    except (OSError, ValueError) as exc:
        raise RunInfoError(f"{path} is not a readable {kind} ({exc})") from exc
    if not isinstance(record, dict):
        raise RunInfoError(f"{path} is not a {kind} (a JSON object)")
    return record
