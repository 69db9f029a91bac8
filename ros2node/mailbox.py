"""A one-slot mailbox between the subscription and the labelling thread, which counts drops.

The subscription callback only puts the message in (with the time it was received); the
labelling thread takes the newest one when it is free. A message that arrives while an older
one still waits replaces it and the older one counts as dropped, so a slow network costs
freshness, never a growing queue.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Received:
    """A message and when it was received (`time.perf_counter()` seconds)."""

    message: Any
    received: float


class Mailbox:
    """Holds at most one `Received`; `put` replaces (and counts) one not taken yet."""

    def __init__(self) -> None:
        self._ready = threading.Condition()
        self._item: Received | None = None
        self._closed = False
        self._dropped = 0

    @property
    def dropped(self) -> int:
        """Messages replaced by a newer one before they were taken."""
        with self._ready:
            return self._dropped

    def put(self, item: Received) -> bool:
        """Leave `item` for the taker; True when it replaced one (a drop)."""
        with self._ready:
            replaced = self._item is not None
            if replaced:
                self._dropped += 1
            self._item = item
            self._ready.notify()
            return replaced

    def take(self) -> Received | None:
        """The newest item, waiting for one; None once the mailbox is closed."""
        with self._ready:
            while self._item is None and not self._closed:
                self._ready.wait()
            if self._closed:
                return None
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        """Wake the taker for good: `take` returns None from now on."""
        with self._ready:
            self._closed = True
            self._ready.notify_all()
