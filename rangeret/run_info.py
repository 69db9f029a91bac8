"""`run.json`: how a predictions tree was made, written beside it by every runner the same way.

It records the network (model, checkpoint and its SHA-256, whether these are the demo weights,
projection, kNN, test-time augmentation, device), the data (dataset, sequences), the batch size,
the runner and the start time, so that any tree can be traced back to what produced it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rangeret.atomic import atomic_write_text

RUN_INFO = "run.json"


def write_run_info(
    out: Path | str,
    network: Mapping[str, Any],
    *,
    runner: str,
    dataset: Path | str,
    sequences: Sequence[str],
    batch_size: int,
) -> Path:
    """Write `OUT/run.json` atomically and return its path.

    `network` is the description of the network and its options (`Predictor.describe()`, or
    `describe_network` where no predictor is loaded in this process).
    """
    record = {
        **network,
        "batch_size": batch_size,
        "dataset": str(dataset),
        "sequences": list(sequences),
        "runner": runner,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    path = Path(out) / RUN_INFO
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    return path
