"""Token mixers of the RetNet blocks (thesis section 3.2.2, Eq. 3.8-3.13, Fig. 3.11).

- `MultiScaleRetention`: the thesis's retention: rotated Q and K, decay-weighted scores, GroupNorm
  over heads, swish gate, output projection.
- `SoftmaxAttention`: the thesis's Transformer baseline (Table 5.8, "Transformers"): the same
  rotated Q and K and doubled V, softmax attention, no gate and no GroupNorm.
- `CircularRetention`: the released network's mixer: softmax over logits plus the log of a decay
  (the circular one by default), each head's output RMS-normalised. Its `g_proj` is part of every
  released checkpoint but unused by the computation.

Each mixer takes (B, N, dim) tokens, the (Hp, Wp) grid they come from and the backbone's
`GridCache`, and returns (B, N, dim). The decay forms of `token_mixing.py` run in the compute dtype
of the pass (the queries' dtype, float16 or bfloat16 under autocast), with decay tables cached in
that dtype; `kernels` picks among them: the tiled forms on the CPU, the fastest exact form on CUDA
(N x N retention or tiled; fused attention with the aligned bias, FlexAttention or tiled).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from rangeret.models.blocks import kernels, token_mixing
from rangeret.models.blocks.decay import GridCache, decay_rates
from rangeret.models.blocks.position import rotate_pairs


def _angle_dtype(dtype: torch.dtype) -> torch.dtype:
    """Precision of the rotary angles for activations of `dtype` (float64 stays float64)."""
    return torch.float64 if dtype == torch.float64 else torch.float32


class _HeadProjections(nn.Module):
    """Bias-free query, key and value projections split into heads, with rotated queries and keys."""

    def __init__(self, dim: int, heads: int, value_factor: int) -> None:
        super().__init__()
        self.heads = heads
        self.key_dim = dim // heads
        self.value_dim = value_factor * dim // heads
        self.q_proj = nn.Linear(dim, dim, bias=False)
        self.k_proj = nn.Linear(dim, dim, bias=False)
        self.v_proj = nn.Linear(dim, value_factor * dim, bias=False)

    def project(
        self, x: torch.Tensor, grid: tuple[int, int], cache: GridCache
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B, heads, N, d) rotated queries, keys scaled by key_dim^-0.5 and rotated, and values."""
        b, n, _ = x.shape
        angles = cache.get("rotary", grid, x.device, _angle_dtype(x.dtype))
        q = self.q_proj(x).view(b, n, self.heads, self.key_dim).transpose(1, 2)
        k = (
            (self.k_proj(x) * self.key_dim**-0.5)
            .view(b, n, self.heads, self.key_dim)
            .transpose(1, 2)
        )
        v = self.v_proj(x).view(b, n, self.heads, self.value_dim).transpose(1, 2)
        return rotate_pairs(q, angles).to(q.dtype), rotate_pairs(k, angles).to(k.dtype), v


class MultiScaleRetention(_HeadProjections):
    """MSR(X) = (swish(X W_G) * GroupNorm_h(concat_h Retention_h(X))) W_O (thesis Eq. 3.12-3.13)."""

    def __init__(self, dim: int, heads: int, value_factor: int) -> None:
        super().__init__(dim, heads, value_factor)
        self.g_proj = nn.Linear(dim, value_factor * dim, bias=False)
        self.out_proj = nn.Linear(value_factor * dim, dim, bias=False)
        self.group_norm = nn.GroupNorm(heads, value_factor * dim)

    def forward(self, x: torch.Tensor, grid: tuple[int, int], cache: GridCache) -> torch.Tensor:
        """(B, N, dim) -> (B, N, dim), parallel form."""
        q, k, v = self.project(x, grid, cache)
        default = "full" if q.device.type == "cuda" else "tiled"
        forms = retention_forms(q, k, v, grid, cache)
        return self._output(x, kernels.run("retention", forms, default, q, v))

    def forward_recurrent(
        self, x: torch.Tensor, grid: tuple[int, int], cache: GridCache
    ) -> torch.Tensor:
        """`forward` computed token by token; defined for the unidirectional decay only."""
        if cache.decay != "unidirectional":
            raise ValueError(
                f"the recurrent form needs the unidirectional decay, not {cache.decay!r}"
            )
        q, k, v = self.project(x, grid, cache)
        gamma = decay_rates(self.heads).to(q.device)
        return self._output(x, token_mixing.retention_recurrent(q, k, v, gamma))

    def _output(self, x: torch.Tensor, mixed: torch.Tensor) -> torch.Tensor:
        """GroupNorm over heads, swish gate and output projection of (B, N, heads, d_v) retention."""
        b, n = mixed.shape[:2]
        y = self.group_norm(mixed.reshape(b * n, -1)).view(b, n, -1)
        return self.out_proj(F.silu(self.g_proj(x)) * y)


class SoftmaxAttention(_HeadProjections):
    """softmax(Q K^T / sqrt(d)) V over rotated Q and K, heads concatenated, then W_O."""

    def __init__(self, dim: int, heads: int, value_factor: int) -> None:
        super().__init__(dim, heads, value_factor)
        self.out_proj = nn.Linear(value_factor * dim, dim, bias=False)

    def forward(self, x: torch.Tensor, grid: tuple[int, int], cache: GridCache) -> torch.Tensor:
        """(B, N, dim) -> (B, N, dim)."""
        b, n, _ = x.shape
        q, k, v = self.project(x, grid, cache)
        return self.out_proj(token_mixing.softmax_fused(q, k, v, None).reshape(b, n, -1))


class CircularRetention(_HeadProjections):
    """Released mixer: softmax(q k^T + log D_h) v per head, RMS-normalised, concatenated, W_O.

    With `decayed=False` (the attention ablation) the bias is left out.
    """

    def __init__(self, dim: int, heads: int, value_factor: int, decayed: bool) -> None:
        super().__init__(dim, heads, value_factor)
        self.decayed = decayed
        self.g_proj = nn.Linear(dim, value_factor * dim, bias=False)
        self.out_proj = nn.Linear(value_factor * dim, dim, bias=False)

    def forward(self, x: torch.Tensor, grid: tuple[int, int], cache: GridCache) -> torch.Tensor:
        """(B, N, dim) -> (B, N, dim)."""
        b, n, _ = x.shape
        q, k, v = self.project(x, grid, cache)
        default = "fused" if q.device.type == "cuda" else "tiled"
        mixed = (
            kernels.run("decayed softmax", self._forms(q, k, v, grid, cache), default, q, v)
            if self.decayed
            else token_mixing.softmax_fused(q, k, v, None)
        )
        mixed = mixed * torch.rsqrt(mixed.pow(2).mean(-1, keepdim=True) + 1e-5)
        return self.out_proj(mixed.reshape(b, n, -1))

    def _forms(
        self,
        q: torch.Tensor,
        k: torch.Tensor,
        v: torch.Tensor,
        grid: tuple[int, int],
        cache: GridCache,
    ) -> dict[str, Callable[[], torch.Tensor]]:
        """The exact forms of softmax with the decay bias, FlexAttention where it compiles."""
        return decayed_softmax_forms(q, k, v, grid, cache, self.heads)


def retention_forms(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    grid: tuple[int, int],
    cache: GridCache,
) -> dict[str, Callable[[], torch.Tensor]]:
    """The exact forms of retention with the decay of `cache`: the whole decay matrix, or tiles of
    its per-grid table."""
    device, dtype = q.device, q.dtype

    def full() -> torch.Tensor:
        decay = cache.get("decay_full", grid, device, dtype)
        return token_mixing.retention_full(q, k, v, decay)

    def tiled() -> torch.Tensor:
        table = cache.get("decay_table", grid, device, dtype)
        norm = cache.get("decay_norm", grid, device, dtype)
        return token_mixing.retention_tiled(q, k, v, table, norm, grid)

    return {"full": full, "tiled": tiled}


def decayed_softmax_forms(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    grid: tuple[int, int],
    cache: GridCache,
    heads: int,
) -> dict[str, Callable[[], torch.Tensor]]:
    """The exact forms of softmax with the decay bias of `cache`, FlexAttention where it compiles."""
    device, dtype = q.device, q.dtype
    decay = cache.decay
    if decay is None:
        raise ValueError("a decayed mixer needs a cache with a decay")

    def fused() -> torch.Tensor:
        bias = cache.get("bias_full", grid, device, dtype)
        return token_mixing.softmax_fused(q, k, v, bias)

    def tiled() -> torch.Tensor:
        table = cache.get("bias_table", grid, device, dtype)
        return token_mixing.softmax_tiled(q, k, v, table, grid)

    def flex() -> torch.Tensor:
        score_mod = token_mixing.decay_score_mod(decay, grid, heads, device)
        return token_mixing.softmax_flex(q, k, v, score_mod)

    forms = {"fused": fused, "tiled": tiled}
    if token_mixing.flex_available(device):
        forms["flex"] = flex
    return forms
