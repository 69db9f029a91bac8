"""Backpressure for single scans: a bound on the requests the gateway holds at once.

A single-scan request is admitted before its body is read, for the bytes its Content-Length
declares (the body limit when it declares none), and holds its place until it is answered: while
its body arrives, while it waits for a batch and while the network runs. Beyond
`max_scans` requests or `max_bytes` body bytes it is refused at once with 503 and `Retry-After`,
so a burst of large scans cannot take the gateway's memory.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Seconds a refused client is asked to wait before it tries again.
RETRY_AFTER_S = 1


class QueueFull(Exception):
    """The gateway holds as many single-scan requests (or body bytes) as it may."""


@dataclass
class ScanAdmission:
    """Counts the single-scan requests and body bytes admitted and not yet answered.

    A request alone is always admitted, whatever its size (the body limit bounds it), so no scan
    is refused for ever. Used from the event loop only, so it needs no lock.
    """

    max_scans: int
    max_bytes: int
    scans: int = 0
    bytes: int = 0

    def admit(self, nbytes: int) -> Place:
        """A place for one request of `nbytes` body bytes, held until its `with` block ends;
        `QueueFull` when it does not fit now."""
        if self.scans >= self.max_scans:
            raise QueueFull(
                f"The gateway holds {self.max_scans:,} single-scan requests, its limit "
                f"(RANGERET_MAX_QUEUED_SCANS); retry in {RETRY_AFTER_S} s."
            )
        if self.scans and self.bytes + nbytes > self.max_bytes:
            raise QueueFull(
                f"The gateway holds {self.bytes:,} bytes of scans, and {nbytes:,} more would pass "
                f"its limit of {self.max_bytes:,} (RANGERET_MAX_QUEUED_BYTES); retry in "
                f"{RETRY_AFTER_S} s."
            )
        self.scans += 1
        self.bytes += nbytes
        return Place(self, nbytes)


@dataclass
class Place:
    """One admitted request's share of the bound; given back when its `with` block ends."""

    admission: ScanAdmission
    nbytes: int

    def __enter__(self) -> Place:
        return self

    def __exit__(self, *_: object) -> None:
        self.admission.scans -= 1
        self.admission.bytes -= self.nbytes
