"""The ways a single-scan labeller can fail a request, which the scans route turns into answers."""

from __future__ import annotations


class BackendError(RuntimeError):
    """The labelling backend failed or cannot be reached (not the request's fault): 503, to be
    retried."""


class BackendTimeout(BackendError):
    """The labelling backend did not answer in time: 504."""


class ScanRejected(ValueError):
    """The workers cannot label this scan because of what it holds (a laser id off the image)."""
