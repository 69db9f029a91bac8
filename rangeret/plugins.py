"""Subcommands and training back-ends contributed by the layers above the library.

The library knows nothing of Ray or HTTP. `workers` and `service` declare what they add to the
`rangeret` command as Python entry points (see `pyproject.toml`):

- group `rangeret.commands`: a `Subcommand` (`serve`, `demo`);
- group `rangeret.train_backends`: a `TrainBackend` (`train --ray`).

An entry point's module must import quickly (no torch, Ray or web stack at import time): it is
loaded to build every parser; its `add_arguments` and `run` import what they need.

A subcommand or back-end names the optional extra it needs (`rangeret.extras`); without that
extra's modules it stops with one line, a `MissingExtraError` naming the extra.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

from rangeret.extras import MissingExtraError, extra_installed, require_extra

if TYPE_CHECKING:
    from rangeret.training.config import TrainConfig

log = logging.getLogger(__name__)

COMMANDS_GROUP = "rangeret.commands"
TRAIN_BACKENDS_GROUP = "rangeret.train_backends"


@dataclass(frozen=True)
class Subcommand:
    """One `rangeret` subcommand: its name, one line of help, its options and its body."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    #: The optional extra the command needs (a key of `EXTRA_MODULES`), or None.
    extra: str | None = None

    def installed(self) -> bool:
        """Whether the command's extra (if it needs one) is installed, so that it can run."""
        return self.extra is None or extra_installed(self.extra)

    def refuse(self, args: argparse.Namespace) -> int:
        """The body of the command without its extra: the one-line `MissingExtraError`."""
        raise MissingExtraError(f"rangeret {self.name}", self.extra or "")


@dataclass(frozen=True)
class TrainBackend:
    """Another place to run `rangeret train`: its options, whether they select it, and its run."""

    add_arguments: Callable[[argparse.ArgumentParser], None]
    selected: Callable[[argparse.Namespace], bool]
    run: Callable[[TrainConfig, argparse.Namespace], None]
    #: The option that selects it, as messages name it (e.g. `--ray`).
    option: str = ""
    #: The optional extra it needs (a key of `EXTRA_MODULES`), or None.
    extra: str | None = None

    def check(self) -> None:
        """`MissingExtraError` (`rangeret train OPTION needs ...`) when its extra is missing."""
        if self.extra is not None:
            require_extra(f"rangeret train {self.option}".rstrip(), self.extra)


def load_plugins(group: str) -> list[Any]:
    """The objects of every entry point of `group`, in name order; one that fails to load is
    logged and left out, so a broken layer never takes the library's own commands down."""
    found = []
    for ep in sorted(entry_points(group=group), key=lambda e: e.name):
        try:
            found.append(ep.load())
        except Exception as exc:
            log.warning("cannot load %s from %s (%s): %s", ep.name, group, ep.value, exc)
    return found
