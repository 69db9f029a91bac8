"""Decay matrices D of retention (thesis Eq. 3.9-3.12, Table 4.6, Fig. 3.12 and 4.12-4.14).

Head h decays with gamma_h = 1 - 2^(-5-h): D_h[n, m] = gamma_h ** g(n, m), where g is a distance
between tokens n and m of the Hp x Wp patch grid (n = row * Wp + col):

- `unidirectional`: n - m for m <= n, masked (D = 0) above the diagonal (RetNet's causal decay);
- `bidirectional`: |n - m|;
- `manhattan`: |row_n - row_m| + |col_n - col_m|;
- `exp-manhattan`: the thesis's, Manhattan distance d mapped by (d / (Hp + Wp - 2))^2 * (N - 1);
- `circular`: the released network's, like `exp-manhattan` but with the column distance taken
  around the azimuth, min(|dc|, Wp - |dc|), and d divided by its largest value on the grid,
  (Hp - 1) + floor(Wp / 2).

The softmax mixers add log D_h = log(gamma_h) * g as a bias to their logits instead.

g(n, m) depends only on the row offset row_m - row_n and the two columns, so one
(Wp, 2 Hp - 1, Wp) table holds every entry: the keys of query (r, c) are
table[c, Hp - 1 - r : 2 Hp - 1 - r, :]. That is what the mixers read, block by block of queries,
instead of an N x N matrix per head (N = 3825 at 64 x 1024). `GridCache` builds the tables once per
grid shape, device and compute dtype, shares them across layers, keeps them out of the state_dict,
and rebuilds them after the module moves. Where a kernel needs the N x N matrix itself, the cache
stores it with rows padded to a multiple of `ALIGN` and hands out the unpadded view, so that fused
attention kernels take it as it is instead of padding a copy on every call.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from rangeret.models.blocks.position import rotary_angles

DECAYS = ("unidirectional", "bidirectional", "manhattan", "exp-manhattan", "circular")

#: Row stride, in elements, of the cached N x N matrices: fused attention kernels copy a bias
#: whose strides are not multiples of 8 on every call.
ALIGN = 8


def decay_rates(heads: int) -> torch.Tensor:
    """(heads,) float64 decay gamma_h = 1 - 2^(-5-h) of each head (thesis Eq. 3.12)."""
    return 1.0 - 2.0 ** (-5.0 - torch.arange(heads, dtype=torch.float64))


def exp_floor(dtype: torch.dtype) -> float | None:
    """Smallest exponent kept when exponentiating in `dtype`; below it a weight is stored as 0.

    e^floor is 0.8 of the way (in log) to the smallest normal number: weights under it are more
    than 20 orders of magnitude below the resolution of float32 next to the diagonal's weight,
    and keeping them subnormal makes x86 arithmetic on them about a hundred times slower.
    float16 has no such margin and keeps everything.
    """
    if dtype == torch.float16:
        return None
    return 0.8 * math.log(torch.finfo(dtype).tiny)


def grid_distance(decay: str, hp: int, wp: int) -> torch.Tensor:
    """(N, N) float64 distance g(n, m) of `decay` on an Hp x Wp grid, inf where D is masked."""
    n = torch.arange(hp * wp, dtype=torch.float64)
    rows, cols = torch.div(n, wp, rounding_mode="floor"), torch.remainder(n, wp)
    row_offset = rows[None, :] - rows[:, None]
    col_n, col_m = cols[:, None], cols[None, :]
    return _distance(decay, hp, wp, row_offset, col_n, col_m)


def distance_table(decay: str, hp: int, wp: int) -> torch.Tensor:
    """(Wp, 2 Hp - 1, Wp) float64 table T[c, j, c'] = g((r, c), (r + j - Hp + 1, c')) for any r."""
    row_offset = (torch.arange(2 * hp - 1, dtype=torch.float64) - (hp - 1))[None, :, None]
    cols = torch.arange(wp, dtype=torch.float64)
    return _distance(decay, hp, wp, row_offset, cols[:, None, None], cols[None, None, :])


def expand_table(table: torch.Tensor, hp: int) -> torch.Tensor:
    """(..., N, N) matrix from a (..., Wp, 2 Hp - 1, Wp) row-offset table."""
    rows = [table[..., hp - 1 - r : 2 * hp - 1 - r, :] for r in range(hp)]
    full = torch.stack(rows, dim=-4)
    return full.flatten(-4, -3).flatten(-2, -1)


def aligned_empty(heads: int, n: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """(heads, N, N) view of a zeroed (heads, N, N rounded up to `ALIGN`) tensor."""
    padded = -(-n // ALIGN) * ALIGN
    return torch.zeros(heads, n, padded, device=device, dtype=dtype)[..., :n]


def token_distance(
    decay: str, grid: tuple[int, int], query: torch.Tensor, key: torch.Tensor
) -> torch.Tensor:
    """g(n, m) of `decay` from broadcastable integer token indices, in float32 (for kernels that
    compute the decay from positions)."""
    hp, wp = grid
    row_offset = torch.div(key, wp, rounding_mode="floor") - torch.div(
        query, wp, rounding_mode="floor"
    )
    return _distance(
        decay,
        hp,
        wp,
        row_offset.to(torch.float32),
        torch.remainder(query, wp).to(torch.float32),
        torch.remainder(key, wp).to(torch.float32),
    )


def _distance(
    decay: str, hp: int, wp: int, row_offset: torch.Tensor, col_n: torch.Tensor, col_m: torch.Tensor
) -> torch.Tensor:
    """g for broadcastable key-row offsets and query/key columns."""
    num_tokens = hp * wp
    col_offset = col_m - col_n
    if decay in ("unidirectional", "bidirectional"):
        lag = -(row_offset * wp + col_offset)
        if decay == "bidirectional":
            return lag.abs()
        return torch.where(lag >= 0, lag, torch.full_like(lag, math.inf))
    if decay == "circular":
        col_dist = torch.minimum(col_offset.abs(), wp - col_offset.abs())
        max_dist = (hp - 1) + wp // 2
    elif decay in ("manhattan", "exp-manhattan"):
        col_dist = col_offset.abs()
        max_dist = hp + wp - 2
    else:
        raise ValueError(f"unknown decay {decay!r}; known: {', '.join(DECAYS)}")
    dist = row_offset.abs() + col_dist
    if decay == "manhattan":
        return dist
    if max_dist == 0:
        return torch.zeros_like(dist)
    return (dist / max_dist) ** 2 * (num_tokens - 1)


class GridCache(nn.Module):
    """What the backbone precomputes per patch grid, shared by all its layers.

    Entries are keyed by (kind, (Hp, Wp), device, dtype) and built on first use: `rotary`
    (2, N, key_dim); `bias_table` log D as a (heads, Wp, 2 Hp - 1, Wp) row-offset table;
    `decay_table` D likewise; `decay_norm` (heads, N) 1 / sqrt(row sums of D); `bias_full` and
    `decay_full` (heads, N, N), the latter already divided by the square root of its row sums, both
    views of rows padded to `ALIGN`. Decay entries are computed in float64 and rounded once to the
    dtype asked for, which is the compute dtype of the pass (float16 or bfloat16 under autocast), so
    no float32 matrix is built for a half-precision pass. Entries are plain attributes, never in the
    state_dict; moving or casting the module drops them, and they are rebuilt where it went.
    """

    KINDS = ("rotary", "bias_table", "decay_table", "decay_norm", "bias_full", "decay_full")

    def __init__(self, decay: str | None, heads: int, key_dim: int) -> None:
        super().__init__()
        self.decay = decay
        self.heads = heads
        self.key_dim = key_dim
        self._entries: dict[tuple[Any, ...], torch.Tensor] = {}

    def get(
        self, kind: str, grid: tuple[int, int], device: torch.device, dtype: torch.dtype
    ) -> torch.Tensor:
        """The `kind` entry for `grid`, built once and then returned as the same tensor."""
        key = (kind, grid, device, dtype)
        entry = self._entries.get(key)
        if entry is None:
            entry = self._build(kind, grid, device, dtype)
            self._entries[key] = entry
        return entry

    def entries(self) -> dict[tuple[Any, ...], torch.Tensor]:
        """A snapshot of what is cached now, by key."""
        return dict(self._entries)

    def _apply(self, fn: Any, *args: Any, **kwargs: Any) -> GridCache:
        """Drop every entry when the module moves or is cast; they are rebuilt on next use."""
        self._entries.clear()
        return super()._apply(fn, *args, **kwargs)

    def _build(
        self, kind: str, grid: tuple[int, int], device: torch.device, dtype: torch.dtype
    ) -> torch.Tensor:
        """Compute one entry on the CPU (float64 for decay, float32 or float64 for angles) and
        place it on `device` in `dtype`."""
        hp, wp = grid
        if kind == "rotary":
            exact = torch.float64 if dtype == torch.float64 else torch.float32
            return rotary_angles(hp * wp, self.key_dim, exact).to(device=device, dtype=dtype)
        if kind not in self.KINDS:
            raise ValueError(f"unknown cache entry {kind!r}; known: {', '.join(self.KINDS)}")
        if self.decay is None:
            raise ValueError(f"{kind} asked of a cache without decay")
        log_decay = torch.log(decay_rates(self.heads))[:, None, None, None] * distance_table(
            self.decay, hp, wp
        )
        if kind == "bias_table":
            return log_decay.to(device=device, dtype=dtype)
        if kind == "bias_full":
            return self._full(log_decay, None, hp, device, dtype)
        decay = torch.exp(log_decay)
        norm = self._row_norm(decay, hp)
        floor = exp_floor(dtype)
        if floor is not None:
            decay = torch.where(log_decay < floor, torch.zeros_like(decay), decay)
        if kind == "decay_table":
            return decay.to(device=device, dtype=dtype)
        if kind == "decay_norm":
            return norm.to(device=device, dtype=dtype)
        return self._full(decay, norm, hp, device, dtype)

    @staticmethod
    def _full(
        table: torch.Tensor,
        norm: torch.Tensor | None,
        hp: int,
        device: torch.device,
        dtype: torch.dtype,
    ) -> torch.Tensor:
        """The aligned (heads, N, N) matrix of a float64 table, each row times `norm` if given;
        expanded one head at a time to bound the float64 memory."""
        heads, n = table.shape[0], hp * table.shape[1]
        full = aligned_empty(heads, n, device, dtype)
        for h in range(heads):
            head = expand_table(table[h], hp)
            full[h].copy_(head if norm is None else head * norm[h, :, None])
        return full

    @staticmethod
    def _row_norm(decay: torch.Tensor, hp: int) -> torch.Tensor:
        """(heads, N) 1 / sqrt(sum over keys of D) from a (heads, Wp, 2 Hp - 1, Wp) table."""
        per_offset = decay.sum(-1)
        sums = [per_offset[:, :, hp - 1 - r : 2 * hp - 1 - r].sum(-1) for r in range(hp)]
        return torch.stack(sums, dim=1).flatten(1).rsqrt()
