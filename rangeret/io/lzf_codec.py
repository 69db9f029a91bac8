"""LZF streams (a `binary_compressed` PCD's body) decompressed straight into one numpy buffer.

python-neo-lzf's `decompress` decodes into a scratch buffer and copies that into a bytes object,
so a stream takes twice its output at its peak. Its extension also exports liblzf's own
`lzf_decompress`, which checks every reference against its buffers' bounds; this module calls it
through ctypes to decode into a buffer the caller keeps. Where the symbol is missing,
`decompress_into` falls back to `decompress` (and its doubled peak).
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable

import numpy as np


@functools.cache
def _liblzf() -> Callable[..., int] | None:
    """liblzf's `lzf_decompress(in, in_len, out, out_len)`, or None where it is not exported."""
    import lzf

    try:
        function = ctypes.CDLL(lzf.__file__).lzf_decompress
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_uint]
    function.restype = ctypes.c_uint
    return function


def decompress_into(stream: np.ndarray, size: int) -> np.ndarray | None:
    """The uint8 `stream` decompressed into a new uint8 array of `size` bytes, or None when it
    is corrupt or does not decompress to exactly `size` bytes."""
    out = np.empty(size, dtype=np.uint8)
    function = _liblzf()
    if function is not None:
        got = function(stream.ctypes.data, len(stream), out.ctypes.data, size) if size else 0
        return out if got == size else None
    import lzf

    try:
        data = lzf.decompress(stream.tobytes(), size)
    except ValueError:
        return None
    if data is None or len(data) != size:
        return None
    out[:] = np.frombuffer(data, dtype=np.uint8)
    return out
