"""What the node reports at each interval: messages labelled, dropped and bad, and latency.

Counts are totals since the start; latency (receive -> publish) and the node's own overhead
(the time besides labelling: message -> record, building and publishing the answer) are
percentiles over the interval's messages. Thread-safe: the labelling thread records, the
report timer reads.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Report:
    """One interval's figures (milliseconds; None where no message was labelled)."""

    labelled: int
    dropped: int
    bad: int
    bad_kinds: dict[str, int]
    interval_labelled: int
    interval_bad: int
    interval_s: float
    latency_p50_ms: float | None
    latency_p95_ms: float | None
    overhead_p50_ms: float | None
    overhead_p95_ms: float | None

    def values(self) -> dict[str, str]:
        """The figures as the diagnostics' key/value strings (see docs/ros2.md)."""
        out = {
            "labelled": str(self.labelled),
            "dropped": str(self.dropped),
            "bad": str(self.bad),
            "interval_s": f"{self.interval_s:.3f}",
            "interval_labelled": str(self.interval_labelled),
            "interval_bad": str(self.interval_bad),
        }
        for key in ("latency_p50_ms", "latency_p95_ms", "overhead_p50_ms", "overhead_p95_ms"):
            value = getattr(self, key)
            out[key] = "n/a" if value is None else f"{value:.3f}"
        out.update({f"bad_{kind}": str(n) for kind, n in sorted(self.bad_kinds.items())})
        return out

    def line(self) -> str:
        """The figures as one log line."""
        text = (
            f"labelled {self.interval_labelled} in the last {self.interval_s:.1f} s "
            f"(total {self.labelled}), dropped {self.dropped}, bad {self.bad}"
        )
        if self.bad_kinds:
            text += " (" + ", ".join(f"{k} {n}" for k, n in sorted(self.bad_kinds.items())) + ")"
        if self.latency_p50_ms is not None:
            text += (
                f"; latency p50 {self.latency_p50_ms:.1f} ms, p95 {self.latency_p95_ms:.1f} ms, "
                f"overhead p50 {self.overhead_p50_ms:.1f} ms"
            )
        return text


def _percentile(samples: list[float], q: float) -> float | None:
    return float(np.percentile(samples, q)) if samples else None


@dataclass
class NodeStats:
    """Counters and the current interval's timings of a running node."""

    _lock: threading.Lock = field(default_factory=threading.Lock)
    _labelled: int = 0
    _bad: dict[str, int] = field(default_factory=dict)
    _latency: list[float] = field(default_factory=list)
    _overhead: list[float] = field(default_factory=list)
    _interval_bad: int = 0

    def labelled(self, latency_s: float, overhead_s: float) -> None:
        """One message labelled and published, `latency_s` after it was received."""
        with self._lock:
            self._labelled += 1
            self._latency.append(1e3 * latency_s)
            self._overhead.append(1e3 * overhead_s)

    def bad(self, kind: str) -> bool:
        """One message skipped for a problem of `kind`; True when it is the first of its kind
        (the one to log)."""
        with self._lock:
            first = kind not in self._bad
            self._bad[kind] = self._bad.get(kind, 0) + 1
            self._interval_bad += 1
            return first

    def report(self, dropped: int, interval_s: float) -> Report:
        """The figures of the interval now ending (`dropped`: the mailbox's count), which
        starts the next one."""
        with self._lock:
            latency, overhead = self._latency, self._overhead
            interval_bad = self._interval_bad
            self._latency, self._overhead, self._interval_bad = [], [], 0
            return Report(
                labelled=self._labelled,
                dropped=dropped,
                bad=sum(self._bad.values()),
                bad_kinds=dict(self._bad),
                interval_labelled=len(latency),
                interval_bad=interval_bad,
                interval_s=interval_s,
                latency_p50_ms=_percentile(latency, 50),
                latency_p95_ms=_percentile(latency, 95),
                overhead_p50_ms=_percentile(overhead, 50),
                overhead_p95_ms=_percentile(overhead, 95),
            )
