"""Memory a process freed, handed back to the system: for a server that frees one network and
builds the next, so that what it holds follows the networks it keeps.

Torch keeps the device memory of freed tensors cached for reuse, and the C allocator keeps freed
heap pages in its arenas (one per thread that allocated), so without this a process that loads
networks in turn on several threads holds the peak of all of them.
"""

from __future__ import annotations

import ctypes

import torch


def release_freed_memory() -> None:
    """Return the memory of tensors already freed: torch's cached CUDA blocks, and the free pages
    of the C allocator's arenas (glibc's `malloc_trim`; a C library without it keeps them)."""
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
    trim = getattr(ctypes.CDLL(None), "malloc_trim", None)
    if trim is not None:
        trim(0)
