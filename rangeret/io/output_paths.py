"""Where outputs really land: every output path resolved (links followed, at any depth) before a
byte is written, so that no route through a symlinked folder makes a command replace its inputs.

`landing_inside` finds outputs that resolve into an input tree (for commands whose whole output
must stay apart from it, such as `rangeret adapt`); `landing_on` finds outputs that resolve onto
an input file itself (for commands that may write beside their inputs, such as `rangeret predict`
with `--out` the dataset's own root). Folders are resolved once each.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path


class _Resolver:
    """Resolved paths, each folder resolved once."""

    def __init__(self) -> None:
        self.folders: dict[str, str] = {}

    def __call__(self, path: Path | str) -> str:
        """`path` with its links resolved, as far as it exists (a missing tail kept)."""
        folder, name = os.path.split(os.path.abspath(path))
        resolved = self.folders.get(folder)
        if resolved is None:
            resolved = self.folders[folder] = os.path.realpath(folder)
        full = os.path.join(resolved, name)
        return os.path.realpath(full) if os.path.islink(full) else full


def landing_inside(outputs: Iterable[Path], root: Path | str) -> tuple[Path, str] | None:
    """The first of `outputs` that resolves to `root` or inside it, with where it resolves to;
    None when every one stays outside."""
    resolve = _Resolver()
    top = os.path.realpath(root)
    for output in outputs:
        target = resolve(output)
        if target == top or target.startswith(top.rstrip(os.sep) + os.sep):
            return output, target
    return None


def landing_on(outputs: Iterable[Path], inputs: Iterable[Path]) -> tuple[Path, Path] | None:
    """The first of `outputs` that resolves to the same file as one of `inputs`, with that
    input; None when none does."""
    resolve = _Resolver()
    taken = {resolve(path): path for path in inputs}
    for output in outputs:
        source = taken.get(resolve(output))
        if source is not None:
            return output, source
    return None
