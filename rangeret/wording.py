"""Small helpers for the sentences the commands print."""

from __future__ import annotations


def plural(count: int, word: str, many: str | None = None) -> str:
    """`count` and `word`, in the plural (`many`, else `word` + "s") unless it is one:
    "1 epoch", "3 epochs"."""
    return f"{count} {word if count == 1 else many or word + 's'}"
