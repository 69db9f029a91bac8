"""What goes wrong when a job is asked for, as the jobs package says it: one sentence each.

The jobs package raises these and knows nothing of HTTP; the routes answer each with its status
(`service.routes.job_errors`).
"""

from __future__ import annotations


class JobInputError(Exception):
    """A job request or upload that cannot become a job, as one sentence."""


class BadJobRequest(JobInputError):
    """The request, or the dataset it names, cannot be used as it is."""


class OutsideDataRoots(JobInputError):
    """The request names data outside the configured data roots, or none are configured."""


class NoSuchDataset(JobInputError):
    """No dataset folder is at the path the request names under the data roots."""


class JobRefused(JobInputError):
    """A job the gateway cannot take now (the queue or the disk is full)."""


class QueueFull(JobRefused):
    """As many jobs wait as the gateway lets wait."""


class NoRoom(JobRefused):
    """The job's files do not fit in the disk the job folders may use, or have."""
