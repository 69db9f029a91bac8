"""Token-mixing arithmetic of retention and attention: plain, tiled and recurrent forms.

All take per-head queries, keys and values (B, heads, N, d) already projected, rotated and scaled,
and return (B, N, heads, d_v).

The plain forms build the (B, heads, N, N) scores at once, literally as the thesis writes them.
The tiled forms give the same result block by block of query tokens: every normalisation in both
networks is per query row, so a block of scores, its decay or bias (a view of the row-offset table
of `decay.py`, never an N x N matrix), its normalisation and its product with V are computed while
the block is still in cache (`benchmarks/bench_models.py` compares the forms on the CPU). The recurrent form is RetNet's O(1)-per-token recurrence, which equals the parallel form
under the unidirectional decay. `softmax_flex` is the softmax form through FlexAttention, with the
decay bias computed from token positions inside the kernel instead of read from a matrix.
`softmax_rows` is the softmax form through torch's fused attention kernel, one grid row of queries
at a time with the bias read from the row-offset table.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
import torch.nn.functional as F

from rangeret.models.blocks.decay import decay_rates, exp_floor, token_distance

#: FlexAttention's score modification: (score, batch, head, query index, key index) -> score.
ScoreMod = Callable[
    [torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor
]

#: Query tokens per tile: 4 heads x 128 x 3825 float32 scores (7.8 MB) stay in the large caches.
TILE = 128


def query_tiles(grid: tuple[int, int], tile: int) -> list[tuple[int, int, int]]:
    """(row, first column, end column) of each block of queries; a block never spans two grid rows."""
    hp, wp = grid
    count = -(-wp // tile)
    bounds = [round(i * wp / count) for i in range(count + 1)]
    return [(r, bounds[i], bounds[i + 1]) for r in range(hp) for i in range(count)]


def retention_plain(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, decay: torch.Tensor
) -> torch.Tensor:
    """Retention (QK^T * D~) V with D~ = D / sqrt(row sums of D) and rows of the product divided by
    max(|row sum|, 1) (thesis Eq. 3.9 and the normalisations after Eq. 3.13); `decay` is D (heads, N, N).
    """
    decay = decay / decay.sum(-1, keepdim=True).sqrt()
    scores = (q @ k.transpose(-1, -2)) * decay
    scores = scores / scores.sum(-1, keepdim=True).abs().clamp(min=1)
    return (scores @ v).transpose(1, 2)


def retention_full(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, decay_full: torch.Tensor
) -> torch.Tensor:
    """`retention_plain` with D~ already normalised (the cached `decay_full`), for GPUs."""
    scores = (q @ k.transpose(-1, -2)) * decay_full
    scale = 1.0 / scores.sum(-1, keepdim=True).abs().clamp(min=1)
    return ((scores @ v) * scale).transpose(1, 2)


def retention_tiled(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    decay_table: torch.Tensor,
    decay_norm: torch.Tensor,
    grid: tuple[int, int],
    tile: int = TILE,
) -> torch.Tensor:
    """`retention_plain` block by block, reading D from its (heads, Wp, 2 Hp - 1, Wp) table.

    The per-row factor 1 / sqrt(row sum of D) (`decay_norm`, (heads, N)) is applied to each block's
    row sums and output rather than to its scores.
    """
    b, h = q.shape[:2]
    hp, wp = grid
    kt = k.transpose(-1, -2)
    blocks = []
    for r, c0, c1 in query_tiles(grid, tile):
        n0, n1 = r * wp + c0, r * wp + c1
        scores = q[:, :, n0:n1] @ kt
        scores.view(b, h, c1 - c0, hp, wp).mul_(decay_table[:, c0:c1, hp - 1 - r : 2 * hp - 1 - r])
        norm = decay_norm[:, n0:n1, None]
        row_sum = scores.sum(-1, keepdim=True) * norm
        blocks.append((scores @ v) * (norm / row_sum.abs().clamp(min=1)))
    return torch.cat(blocks, dim=2).transpose(1, 2)


def retention_recurrent(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, gamma: torch.Tensor
) -> torch.Tensor:
    """Retention with the unidirectional decay, one token at a time (RetNet's recurrent form).

    State S_n = gamma S_(n-1) + k_n^T v_n, with z_n = gamma z_(n-1) + k_n and c_n = gamma c_(n-1) + 1
    tracking the two normalisations: o_n = q_n S_n / sqrt(c_n) / max(|q_n z_n| / sqrt(c_n), 1).
    """
    b, h, n, dk = q.shape
    g = gamma.to(q.dtype)
    state = q.new_zeros(b, h, dk, v.shape[-1])
    key_sum = q.new_zeros(b, h, dk)
    count = q.new_zeros(h)
    outputs = []
    for i in range(n):
        state = g[:, None, None] * state + k[:, :, i, :, None] * v[:, :, i, None, :]
        key_sum = g[:, None] * key_sum + k[:, :, i]
        count = g * count + 1
        root = count.sqrt()[:, None]
        out = (q[:, :, i, None, :] @ state)[:, :, 0] / root
        row_sum = (q[:, :, i] * key_sum).sum(-1, keepdim=True) / root
        outputs.append(out / row_sum.abs().clamp(min=1))
    return torch.stack(outputs, dim=1)


def softmax_plain(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor | None
) -> torch.Tensor:
    """softmax(q k^T + bias) v over keys; `bias` (heads, N, N) or None."""
    logits = q @ k.transpose(-1, -2)
    if bias is not None:
        logits = logits + bias
    return (torch.softmax(logits, dim=-1) @ v).transpose(1, 2)


def softmax_fused(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor | None
) -> torch.Tensor:
    """`softmax_plain` through torch's fused attention kernels (flash / memory-efficient).

    A bias in q's dtype whose row stride is a multiple of 8 (`GridCache`'s `bias_full`) is read in
    place; any other is cast or padded by torch on every call.
    """
    mask = None if bias is None else bias.to(q.dtype)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=1.0).transpose(1, 2)


def softmax_tiled(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    bias_table: torch.Tensor,
    grid: tuple[int, int],
    tile: int = TILE,
) -> torch.Tensor:
    """`softmax_plain` block by block, reading the bias from its (heads, Wp, 2 Hp - 1, Wp) table.

    Without autograd each block is exponentiated in place and divided by its row sums after the
    product with V (a (rows, d_v) division instead of (rows, N)); exponents are clamped at
    `exp_floor` so that no subnormal weights reach the product.
    """
    b, h, n, _ = q.shape
    hp, wp = grid
    kt = k.transpose(-1, -2)
    grad = torch.is_grad_enabled() and any(t.requires_grad for t in (q, k, v))
    floor = exp_floor(q.dtype)
    blocks = []
    for r, c0, c1 in query_tiles(grid, tile):
        n0, n1 = r * wp + c0, r * wp + c1
        bias = bias_table[:, c0:c1, hp - 1 - r : 2 * hp - 1 - r]
        logits = q[:, :, n0:n1] @ kt
        if grad:
            logits = (logits.view(b, h, c1 - c0, hp, wp) + bias).view(b, h, c1 - c0, n)
            blocks.append(torch.softmax(logits, dim=-1) @ v)
            continue
        logits.view(b, h, c1 - c0, hp, wp).add_(bias)
        logits.sub_(logits.amax(-1, keepdim=True))
        if floor is not None:
            logits.clamp_(min=floor)
        weights = logits.exp_()
        blocks.append((weights @ v).div_(weights.sum(-1, keepdim=True)))
    return torch.cat(blocks, dim=2).transpose(1, 2)


def softmax_rows(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    bias_table: torch.Tensor,
    grid: tuple[int, int],
) -> torch.Tensor:
    """`softmax_plain` one grid row of queries at a time through torch's fused attention kernel,
    the bias of each row a view of the (heads, Wp, 2 Hp - 1, Wp) table (never an N x N matrix).

    The fused CPU kernel computes the logits, the softmax and the product with V tile by tile in
    cache (with float32 sums for half-precision inputs), where the tiled form makes seven passes
    over each block of scores. It takes queries and keys as wide as the values only: narrower
    ones are padded with zeros, which leaves q k^T unchanged (`pad_heads` does it once).
    """
    b, h, n, dv = v.shape
    hp, wp = grid
    q, k = pad_heads(q, dv), pad_heads(k, dv)
    out = v.new_empty(b, n, h, dv)
    for r in range(hp):
        bias = bias_table[:, :, hp - 1 - r : 2 * hp - 1 - r].flatten(2)
        rows = slice(r * wp, (r + 1) * wp)
        out[:, rows] = F.scaled_dot_product_attention(
            q[:, :, rows], k, v, attn_mask=bias[None], scale=1.0
        ).transpose(1, 2)
    return out


def pad_heads(x: torch.Tensor, width: int) -> torch.Tensor:
    """(B, heads, N, d) zero-padded to (B, heads, N, width); `x` itself when already that wide."""
    if x.shape[-1] == width:
        return x
    return F.pad(x, (0, width - x.shape[-1]))


def flex_available(device: torch.device) -> bool:
    """Whether FlexAttention can be compiled for `device`: CUDA with Triton and a torch that has it."""
    if device.type != "cuda":
        return False
    try:
        import torch.nn.attention.flex_attention  # noqa: F401
        from torch.utils._triton import has_triton
    except ImportError:
        return False
    return has_triton()


@functools.cache
def decay_score_mod(
    decay: str, grid: tuple[int, int], heads: int, device: torch.device
) -> ScoreMod:
    """Score modification adding log D_h[n, m] = log(gamma_h) g(n, m), g from the token indices;
    one function per arguments, so that the compiled kernel is reused rather than rebuilt."""
    log_gamma = torch.log(decay_rates(heads)).to(device=device, dtype=torch.float32)

    def score_mod(
        score: torch.Tensor,
        batch: torch.Tensor,
        head: torch.Tensor,
        query: torch.Tensor,
        key: torch.Tensor,
    ) -> torch.Tensor:
        return score + log_gamma[head] * token_distance(decay, grid, query, key)

    return score_mod


def softmax_flex(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, score_mod: ScoreMod
) -> torch.Tensor:
    """`softmax_plain` through FlexAttention with the bias from `score_mod`, compiled on CUDA.

    Elsewhere FlexAttention runs its eager reference, which materialises the scores; that serves to
    check the score modification, not to run fast.
    """
    return _flex_kernel(q.device.type)(q, k, v, score_mod=score_mod, scale=1.0).transpose(1, 2)


@functools.cache
def _flex_kernel(device_type: str) -> Callable[..., torch.Tensor]:
    """flex_attention, compiled once per process for CUDA."""
    from torch.nn.attention.flex_attention import flex_attention

    if device_type == "cuda":
        return torch.compile(flex_attention, dynamic=False)
    return flex_attention
