"""The errors a user can cause or fix, one hierarchy for the whole project.

Every error that means bad input, a wrong setting or something missing from the machine derives
from `RangeRetError`; a command shows it as one line (`rangeret.commands.run_command`). Any other
exception is a bug and keeps its traceback. Domain errors (`ScanFormatError`, `CheckpointError`,
...) derive from one of the kinds below, and also from `ValueError` or `FileNotFoundError` where
callers catch them that way. A leaf module: it imports nothing of the project.
"""

from __future__ import annotations

from collections.abc import Sequence


class RangeRetError(Exception):
    """A problem the user can fix: shown as one line, with the problems found below it."""

    #: Every problem found, each naming its file or value; empty when the message says it all.
    problems: Sequence[str] = ()

    def summary(self) -> str:
        """The one line to show: the message, the one problem, or how many there are (each then
        listed once, by `detail_lines`)."""
        n = len(self.problems)
        if n == 1:
            return self.problems[0]
        return f"{n} problems:" if n else str(self)

    def detail_lines(self) -> list[str]:
        """The lines to show below the summary: every problem, where there are several."""
        return list(self.problems) if len(self.problems) > 1 else []


class InputError(RangeRetError):
    """A file or value given to a command that cannot be used: a scan, a report, an option."""


class InputFileMissing(InputError, FileNotFoundError):
    """A file a command was given does not exist; reads as the `FileNotFoundError` it replaces."""

    @classmethod
    def of(cls, exc: FileNotFoundError) -> InputFileMissing:
        """The same error (number, message, file name) as one a command reports in one line."""
        return cls(exc.errno, exc.strerror, exc.filename)


class DatasetError(RangeRetError):
    """A dataset, predictions tree or submission archive that is incomplete or laid out wrong."""


class ConfigError(RangeRetError):
    """A configuration that cannot be used: a profile, label configuration, YAML file, setting."""


class ModelError(RangeRetError):
    """A network that cannot be had or run: a checkpoint, published weights, an ONNX export."""


class ResourceError(RangeRetError):
    """Something the run needs is not there: a CUDA device, a package, GPUs on the cluster."""


#: The distribution whose extras `pip install` names.
DISTRIBUTION = "rangeret-service"


class MissingExtraError(ResourceError, ValueError):
    """A feature whose optional extra is not installed; its message is the one line to show:
    `FEATURE needs the EXTRA extra: pip install 'rangeret-service[EXTRA]'`."""

    def __init__(self, feature: str, extra: str) -> None:
        super().__init__(
            f"{feature} needs the {extra} extra: pip install '{DISTRIBUTION}[{extra}]'"
        )
        self.feature = feature
        self.extra = extra


class CommandError(RangeRetError):
    """A failure a command reports as one line, with optional details below it."""

    def __init__(self, reason: str, details: Sequence[str] = ()) -> None:
        super().__init__(reason)
        self.reason = reason
        self.details = list(details)

    def summary(self) -> str:
        """The reason, as given."""
        return self.reason

    def detail_lines(self) -> list[str]:
        """The details, as given."""
        return list(self.details)
