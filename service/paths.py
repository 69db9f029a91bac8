"""Where the gateway may read: paths are judged by their real location, links resolved.

A dataset job reads only files whose real path lies under a data root (or, for an uploaded
archive, under the jobs folder), so a link inside a root that points elsewhere is refused rather
than followed. Messages name scans by their key (`08/000001`), never by a server path.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from rangeret.dataset.layout import ScanEntry


def is_inside(path: Path, roots: Sequence[Path]) -> bool:
    """Whether `path`, links resolved, lies under one of `roots` (which are resolved already)."""
    real = Path(os.path.realpath(path))
    return any(real.is_relative_to(root) for root in roots)


def escaping_scans(entries: Iterable[ScanEntry], roots: Sequence[Path]) -> list[str]:
    """The keys of the scans whose scan or label file lies outside `roots` once links are
    resolved."""
    return [
        entry.key
        for entry in entries
        if not all(is_inside(path, roots) for path in (entry.scan_path, entry.label_path) if path)
    ]


def outside_roots_sentence(keys: Sequence[str], what: str = "The dataset") -> str:
    """The refusal for scans that lead outside the roots, naming the first by its key only."""
    return (
        f"{what} has {len(keys)} scan(s) whose files lie outside the data roots once links are "
        f"resolved (the first: {keys[0]}), so it is not read"
    )
