"""Counting the calls that make the host wait for a CUDA device, so that tests on the CPU can check
how often a batch step would wait on a GPU."""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Iterator

import pytest
import torch

#: Tensor methods that make the host wait for a CUDA device (they read its data).
SYNCING = ("item", "tolist", "cpu", "__bool__", "__int__", "__float__", "__index__")
#: Host waits per batch refinement: the copy of the result (its inputs were checked where their
#: `Projection` was made, on the host). However many scans, points and chunks.
SYNCS_PER_BATCH = 1


@contextlib.contextmanager
def host_syncs() -> Iterator[Counter]:
    """Count, by name, the calls in the body that would make the host wait for a CUDA device.

    The reads of `SYNCING`, `nonzero` (its shape depends on the data) and indexing with a boolean
    mask (which is a `nonzero`).
    """
    counts: Counter = Counter()

    def counted(name, original):
        def wrapper(*args, **kwargs):
            counts[name] += 1
            return original(*args, **kwargs)

        return wrapper

    def masked(name, original):
        def wrapper(self, index, *args):
            parts = index if isinstance(index, tuple) else (index,)
            if any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in parts):
                counts[name] += 1
            return original(self, index, *args)

        return wrapper

    with pytest.MonkeyPatch.context() as patch:
        for name in SYNCING:
            patch.setattr(torch.Tensor, name, counted(name, getattr(torch.Tensor, name)))
        patch.setattr(torch.Tensor, "nonzero", counted("nonzero", torch.Tensor.nonzero))
        patch.setattr(torch, "nonzero", counted("nonzero", torch.nonzero))
        for name in ("__getitem__", "__setitem__"):
            patch.setattr(torch.Tensor, name, masked(name, getattr(torch.Tensor, name)))
        yield counts
