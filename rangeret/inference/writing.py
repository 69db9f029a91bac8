"""Writing one scan's prediction into a predictions tree: the step every dataset runner shares.

Where the files go and how wide a label is are the scan's (its layout chose them when it was
listed: `sequences/XX/predictions/NNNNNN.label` of uint32, or nuScenes'
`lidarseg/<split>/<token>_lidarseg.bin` of uint8); each file is written atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangeret.dataset.layout import ScanEntry
from rangeret.io.scans import write_confidence


def write_prediction(
    entry: ScanEntry, out: Path | str, labels: np.ndarray, confidence: np.ndarray | None = None
) -> None:
    """Write a scan's labels (and its points' confidences, when given) into the tree `out`."""
    if confidence is not None:
        write_confidence(entry.confidence_in(out), confidence)
    entry.label_file.write(entry.prediction_in(out), labels)
