"""The leaderboard metadata of a submission: the three lines that open `description.txt`.

The SemanticKITTI benchmark on Codabench reads the start of an archive's `description.txt` as

    name: METHOD NAME
    pdf url: URL OF THE PAPER
    code url: URL OF THE CODE

and shows a method without them as Anonymous with n/a links, so the defaults here are exactly
what it shows then (`Anonymous`, `n/a`, `n/a`). What a run records about itself (the
checkpoint's SHA-256, the model, the profile, the runner, the demo-weights note, free text)
follows on later lines, which the benchmark ignores. `description_text` builds the file for every runner (`rangeret submission`,
the Ray job, the demo and the gateway's prediction archives); `description_problems` checks it
for the submission validator. Torch-free.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

from rangeret.exceptions import InputError
from rangeret.models.weights.demo import demo_warning

DEFAULT_NAME = "Anonymous"
DEFAULT_URL = "n/a"

#: The keys of the first three lines, in order.
KEYS = ("name", "pdf url", "code url")

#: The command-line option of each field, for messages.
OPTIONS = {"name": "--method-name", "pdf_url": "--pdf-url", "code_url": "--code-url"}

_URL = re.compile(r"^https?://\S+$")


class LeaderboardError(InputError, ValueError):
    """A leaderboard value that cannot be written: empty, more than one line, or not a link."""


def value_problem(key: str, value: str) -> str | None:
    """Why `value` cannot follow `key:` on its line (empty, a line break, a link that is neither
    an http(s) URL nor n/a), or None."""
    if "\n" in value or "\r" in value:
        return "holds a line break (description.txt takes one line per value)"
    if not value.strip():
        return "is empty"
    if key != "name" and value.strip() != DEFAULT_URL and not _URL.match(value.strip()):
        return f"is neither an http(s) URL nor {DEFAULT_URL}"
    return None


@dataclass(frozen=True)
class LeaderboardEntry:
    """The method's name and the links of its paper and code, as the leaderboard shows them."""

    name: str = DEFAULT_NAME
    pdf_url: str = DEFAULT_URL
    code_url: str = DEFAULT_URL

    def __post_init__(self) -> None:
        for attr, key in zip(("name", "pdf_url", "code_url"), KEYS, strict=True):
            value = getattr(self, attr)
            problem = value_problem(key, value)
            if problem:
                raise LeaderboardError(f"{OPTIONS[attr]} {value!r} {problem}")
            object.__setattr__(self, attr, value.strip())

    @classmethod
    def from_values(
        cls, name: str | None = None, pdf_url: str | None = None, code_url: str | None = None
    ) -> LeaderboardEntry:
        """An entry from optional values; each missing one takes the benchmark's default."""
        return cls(
            name=DEFAULT_NAME if name is None else name,
            pdf_url=DEFAULT_URL if pdf_url is None else pdf_url,
            code_url=DEFAULT_URL if code_url is None else code_url,
        )

    def lines(self) -> list[str]:
        """The three lines the leaderboard reads, in its order."""
        return [f"name: {self.name}", f"pdf url: {self.pdf_url}", f"code url: {self.code_url}"]


def description_text(
    entry: LeaderboardEntry,
    *,
    written_by: str,
    checkpoint_sha256: str | None,
    model: str | None = None,
    profile: str | None = None,
    demo_weights: bool = False,
    notes: Sequence[str] = (),
) -> str:
    """The whole `description.txt`: the leaderboard's three lines, then what the run records
    (checkpoint SHA-256, model, profile, runner, the demo-weights note, notes); every runner
    writes it through here."""
    lines = entry.lines()
    lines.append(f"checkpoint sha256: {checkpoint_sha256 or 'unknown'}")
    if model:
        lines.append(f"model: {model}")
    if profile:
        lines.append(f"profile: {profile}")
    lines.append(f"written by: {written_by}")
    if demo_weights:
        lines.append(f"NOTE: {demo_warning(profile)}")
    lines += [line for note in notes for line in note.strip().splitlines()]
    return "\n".join(lines) + "\n"


def description_problems(text: str) -> list[str]:
    """Why a `description.txt` would leave the leaderboard's name or links unset or odd, or []."""
    lines = text.splitlines()
    for i, key in enumerate(KEYS):
        line = lines[i] if i < len(lines) else None
        head, sep, value = (line or "").partition(":")
        if line is None or not sep or head.strip().lower() != key:
            found = f"found {line[:60]!r}" if line is not None else "the file ends before it"
            return [
                f"line {i + 1} should be '{key}: ...' ({found}); without the lines name, pdf url "
                f"and code url first, the leaderboard shows the method as {DEFAULT_NAME} with "
                f"{DEFAULT_URL} links"
            ]
        problem = value_problem(key, value)
        if problem:
            return [f"line {i + 1} '{line[:80]}': the value {problem}"]
    return []
