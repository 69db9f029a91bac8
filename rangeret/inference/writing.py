"""Writing one scan's prediction into a predictions tree: the step every dataset runner shares.

Where the files go and how wide a label is are the scan's (its layout chose them when it was
listed: `sequences/XX/predictions/NNNNNN.label` of uint32, or nuScenes'
`lidarseg/<split>/<token>_lidarseg.bin` of uint8); each file is written atomically. Before a run
writes any, `check_outputs_apart` makes sure none of them resolves onto one of its inputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rangeret.dataset.layout import ScanEntry
from rangeret.exceptions import InputError
from rangeret.io.output_paths import landing_on
from rangeret.io.run_info import RUN_INFO
from rangeret.io.scans import write_confidence


class OutputOverInputError(InputError, ValueError):
    """An output path that resolves onto one of the run's input files."""


def check_outputs_apart(entries: Sequence[ScanEntry], out: Path | str) -> None:
    """`OutputOverInputError` when a file the run would write into `out` (a prediction, its
    confidences, run.json) resolves, through links at any depth, onto one of the scans' files or
    labels: a run never replaces what it reads, `--overwrite` or not."""
    out = Path(out)
    outputs = [out / RUN_INFO]
    for entry in entries:
        outputs += [entry.prediction_in(out), entry.confidence_in(out)]
    inputs = [e.scan_path for e in entries] + [e.label_path for e in entries if e.label_path]
    landed = landing_on(outputs, inputs)
    if landed is not None:
        raise OutputOverInputError(
            f"{landed[0]} leads to the input file {landed[1]}: choose an output folder whose "
            "paths do not lead into the dataset's files (inputs are never replaced)"
        )


def write_prediction(
    entry: ScanEntry, out: Path | str, labels: np.ndarray, confidence: np.ndarray | None = None
) -> None:
    """Write a scan's labels (and its points' confidences, when given) into the tree `out`."""
    if confidence is not None:
        write_confidence(entry.confidence_in(out), confidence)
    entry.label_file.write(entry.prediction_in(out), labels)
