"""Inference forms of the blocks: the same functions as the training blocks, rearranged for speed.

Each form is built once from a block in eval mode, holds its weights as buffers in the compute
dtype (float32 or bfloat16), converted once so that no pass casts a weight, and leaves the block it
came from unchanged. The stem's forms are in `rangeret.models.blocks.inference_stem`; here:

- `FastEmbedding`: the VEM, whose float32 tokens start the backbone's float32 residual stream;
- `FastMixer`: one projection for queries, keys, values (and the gate), with the key scale and the
  pair swap of the rotary rotation folded into the weights; on the CPU the softmax mixers run
  torch's fused attention kernel (in bfloat16 with the decay bias too), elsewhere the training
  block's choice of form;
- `FastConvFeedForward`: the depthwise convolution reads the tokens in place as a channels-last
  image and applies the GELU itself;
- `FoldedHead`: its BatchNorm, which follows a Linear, folded into that Linear (`mlp1`), and the
  last Linear in float32.

In bfloat16, what stays float32 is what decides labels for little time: the residual stream and
its LayerNorms (`FastEmbedding`) and the logits (`FoldedHead`); each says why. Decay tables and
rotary angles come from the backbone's `GridCache`, built once per grid, device and dtype.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from rangeret.models.blocks import kernels, token_mixing
from rangeret.models.blocks.decay import GridCache
from rangeret.models.blocks.embedding import PatchEmbedding, require_patch
from rangeret.models.blocks.ffn import ConvFeedForward, FeedForward
from rangeret.models.blocks.head import SemanticHead
from rangeret.models.blocks.inference_stem import (
    ConvAct,
    batchnorm_affine,
    converted,
    shifted_input_bias,
    weight_buffer,
)
from rangeret.models.blocks.retention import (
    CircularRetention,
    MultiScaleRetention,
    SoftmaxAttention,
    decayed_softmax_forms,
    retention_forms,
)

#: Largest N x N decay bias (all heads, in the compute dtype) the fused attention kernel reads
#: whole, cached once per grid: one call over all queries runs a fifth to a quarter faster than
#: one per grid row (bfloat16: 29 MB at 64 x 512, 117 MB at 64 x 1024). A larger matrix, which
#: grows with the square of the grid, is read row by row from its (heads, Wp, 2 Hp - 1, Wp) table.
FULL_BIAS_BYTES = 128 * 2**20


def _swapped_rows(weight: torch.Tensor) -> torch.Tensor:
    """Rows of W such that x W'^T is the pair swap (x0, x1) -> (-x1, x0) of x W^T, per pair of
    output channels: the second half of the rotary rotation, folded into the projection."""
    pairs = weight.unflatten(0, (-1, 2))
    return torch.stack((-pairs[:, 1], pairs[:, 0]), dim=1).flatten(0, 1)


class FastMixer(nn.Module):
    """A token mixer of the backbone with one projection x -> [q, q', k, k', v (, g)].

    q' and k' are the pair-swapped projections, so that the rotary rotation is q cos + q' sin
    without a permutation pass; keys carry the key_dim^-0.5 scale in their weights. `kind` is
    "circular" (the released mixer: softmax with the decay bias, RMS-normalised heads),
    "softmax" (plain softmax attention, heads RMS-normalised or not: `rms`), or "retention" (the
    thesis's: decay-weighted retention, GroupNorm, swish gate). With `fused` (the CPU) the softmax
    mixers run torch's fused attention kernel, in half precision the decayed one too, with its
    N x N bias up to `FULL_BIAS_BYTES` and row by row of the grid beyond
    (`token_mixing.softmax_rows`); otherwise the training block's choice of form runs (on the CPU
    the tiled form).
    """

    def __init__(self, mixer: nn.Module, dtype: torch.dtype, fused: bool) -> None:
        super().__init__()
        self.fused = fused
        # float32 takes the tiled decayed softmax: the fused kernel needs keys as wide as the
        # values, and the padding doubles q k^T, which costs float32 more than fusing saves
        self.fused_decay = fused and dtype != torch.float32
        self.heads, self.key_dim, self.value_dim = mixer.heads, mixer.key_dim, mixer.value_dim
        self.rms = isinstance(mixer, CircularRetention)
        if isinstance(mixer, CircularRetention):
            self.kind = "circular" if mixer.decayed else "softmax"
        elif isinstance(mixer, SoftmaxAttention):
            self.kind = "softmax"
        elif isinstance(mixer, MultiScaleRetention):
            self.kind = "retention"
        else:
            raise TypeError(f"no inference form for {type(mixer).__name__}")
        wq, wk = mixer.q_proj.weight.detach().double(), mixer.k_proj.weight.detach().double()
        wk = wk * self.key_dim**-0.5
        parts = [wq, _swapped_rows(wq), wk, _swapped_rows(wk), mixer.v_proj.weight.detach()]
        if self.kind == "retention":
            parts.append(mixer.g_proj.weight.detach())
            self.group_norm = converted(mixer.group_norm, dtype)
        self.register_buffer("weight", torch.cat([p.double() for p in parts]).to(dtype))
        self.register_buffer("out_weight", weight_buffer(mixer.out_proj.weight, dtype))

    def forward(self, x: torch.Tensor, grid: tuple[int, int], cache: GridCache) -> torch.Tensor:
        """(B, N, dim) -> (B, N, dim)."""
        b, n, dim = x.shape
        h, dk, dv = self.heads, self.key_dim, self.value_dim
        y = F.linear(x, self.weight)
        angles = cache.get("rotary", grid, x.device, torch.float32)
        pairs = y[..., : 4 * dim].view(b, n, 2, 2, h, dk)
        cos, sin = angles[0][:, None, None], angles[1][:, None, None]
        rotated = pairs[:, :, :, 0] * cos + pairs[:, :, :, 1] * sin
        values = y[..., 4 * dim : 4 * dim + h * dv].view(b, n, h, dv).transpose(1, 2)
        padded = self.fused if self.kind == "softmax" else self.fused_decay
        qk = rotated.new_zeros(2, b, h, n, dv if padded else dk, dtype=x.dtype)
        qk[..., :dk] = rotated.permute(2, 0, 3, 1, 4)
        mixed = self._mix(qk[0], qk[1], values, grid, cache)
        if self.kind == "retention":
            mixed = self.group_norm(mixed.reshape(b * n, -1)).view(b, n, -1)
            mixed = F.silu(y[..., 4 * dim + h * dv :]) * mixed
        elif self.rms:
            mixed = F.rms_norm(mixed, (dv,), eps=1e-5)
        return F.linear(mixed.reshape(b, n, -1), self.out_weight)

    def _mix(
        self,
        q: torch.Tensor,
        k: torch.Tensor,
        v: torch.Tensor,
        grid: tuple[int, int],
        cache: GridCache,
    ) -> torch.Tensor:
        """(B, N, heads, d_v) mixed values of rotated queries and keys."""
        device, dtype = q.device, q.dtype
        if self.kind == "softmax":
            return F.scaled_dot_product_attention(q, k, v, scale=1.0).transpose(1, 2)
        if self.kind == "circular" and self.fused_decay:
            n = grid[0] * grid[1]
            if self.heads * n * n * dtype.itemsize <= FULL_BIAS_BYTES:
                bias = cache.get("bias_full", grid, device, dtype)[None]  # 4-D, or the math path
                mixed = F.scaled_dot_product_attention(q, k, v, attn_mask=bias, scale=1.0)
                return mixed.transpose(1, 2)
            # A float32 table: the kernel adds the bias in float32 and reads a float32 one
            # faster than it converts a bfloat16 one.
            table = cache.get("bias_table", grid, device, torch.float32)
            return token_mixing.softmax_rows(q, k, v, table, grid)
        if self.kind == "circular":
            forms = decayed_softmax_forms(q, k, v, grid, cache, self.heads)
            default = "fused" if device.type == "cuda" else "tiled"
            return kernels.run("decayed softmax", forms, default, q, v)
        default = "full" if device.type == "cuda" else "tiled"
        return kernels.run("retention", retention_forms(q, k, v, grid, cache), default, q, v)


class FastConvFeedForward(nn.Module):
    """`ConvFeedForward`: fc1 -> depthwise 3x3 conv with the GELU in its kernel -> fc2, the
    tokens read as a channels-last (B, C, Hp, Wp) image without a copy."""

    def __init__(self, ffn: ConvFeedForward, dtype: torch.dtype, fused: bool) -> None:
        super().__init__()
        self.register_buffer("w1", weight_buffer(ffn.fc1.weight, dtype))
        self.register_buffer("b1", weight_buffer(ffn.fc1.bias, dtype))
        self.dwconv = ConvAct(ffn.dwconv.dwconv, "gelu", dtype, fused)
        self.register_buffer("w2", weight_buffer(ffn.fc2.weight, dtype))
        self.register_buffer("b2", weight_buffer(ffn.fc2.bias, dtype))

    def forward(self, x: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
        """(B, N, dim) -> (B, N, dim)."""
        b, n, _ = x.shape
        hidden = F.linear(x, self.w1, self.b1)
        image = hidden.view(b, grid[0], grid[1], -1).permute(0, 3, 1, 2)
        hidden = self.dwconv(image).permute(0, 2, 3, 1).reshape(b, n, -1)
        return F.linear(hidden, self.w2, self.b2)


class FastEmbedding(nn.Module):
    """`PatchEmbedding`: the patch convolution in the compute dtype (with the stem's `input_shift`
    folded into its bias: it has no padding), its LayerNorm in float32.

    The tokens it gives are float32, and the backbone keeps its residual stream in float32: the
    stream is small (N x dim, a sixteenth of the pixels at stride 4), and rounding it to bfloat16
    at every block changes more labels than any other step of a bfloat16 pass.
    """

    def __init__(
        self,
        embedding: PatchEmbedding,
        dtype: torch.dtype,
        fused: bool,
        input_shift: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        self.patch_size = embedding.patch_size
        bias = shifted_input_bias(embedding.proj, input_shift)
        self.proj = ConvAct(embedding.proj, "none", dtype, fused, bias=bias)
        self.norm = converted(embedding.norm, torch.float32)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        """(B, C, H, W) features -> float32 (B, Hp*Wp, C) tokens in row-major grid order, (Hp, Wp)."""
        require_patch(x, self.patch_size)
        patches = self.proj(x)
        grid = (patches.shape[-2], patches.shape[-1])
        return self.norm(patches.flatten(2).transpose(1, 2).float()), grid


def fast_ffn(ffn: nn.Module, dtype: torch.dtype, fused: bool) -> nn.Module:
    """The inference form of a feed-forward sub-layer (the thesis's plain FFN converted)."""
    if isinstance(ffn, ConvFeedForward):
        return FastConvFeedForward(ffn, dtype, fused)
    if isinstance(ffn, FeedForward):
        return converted(ffn, dtype)
    raise TypeError(f"no inference form for {type(ffn).__name__}")


class FoldedHead(nn.Module):
    """`SemanticHead` with a BatchNorm folded into `mlp1` (a LayerNorm stays, being per pixel),
    and the per-channel shift the stem left out of the residual features (`residual_shift`) too.

    `mlp2` runs in float32 on float32 features whatever the compute dtype: rounding the logits
    themselves to bfloat16 (8 significant bits) turns close classes into ties, which argmax breaks
    towards the lower class; the float32 product costs one cast of the (B, H, W, hidden) features.
    """

    def __init__(
        self, head: SemanticHead, dtype: torch.dtype, residual_shift: torch.Tensor | None = None
    ) -> None:
        super().__init__()
        w1, b1 = head.mlp1.weight.detach().double(), head.mlp1.bias.detach().double()
        if residual_shift is not None:
            b1 = b1 + w1 @ residual_shift.to(w1.device)
        self.layer_norm: nn.Module | None = None
        if isinstance(head.norm, nn.BatchNorm2d):
            scale, shift = batchnorm_affine(head.norm)
            w1, b1 = w1 * scale[:, None], b1 * scale + shift
        else:
            self.layer_norm = converted(head.norm, dtype)
        self.register_buffer("w1", w1.to(dtype))
        self.register_buffer("b1", b1.to(dtype))
        self.register_buffer("w2", weight_buffer(head.mlp2.weight, torch.float32))
        self.register_buffer("b2", weight_buffer(head.mlp2.bias, torch.float32))

    def forward(
        self,
        tokens: torch.Tensor,
        grid: tuple[int, int],
        size: tuple[int, int],
        residual: torch.Tensor | None,
    ) -> torch.Tensor:
        """(B, Hp*Wp, dim) tokens and optional (B, dim, H, W) REM features -> float32
        (B, classes, H, W)."""
        b, _, c = tokens.shape
        x = tokens.reshape(b, grid[0], grid[1], c).permute(0, 3, 1, 2)
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        if residual is not None:
            x = x.add_(residual)
        x = F.linear(x.permute(0, 2, 3, 1), self.w1, self.b1)
        if self.layer_norm is not None:
            x = self.layer_norm(x)
        x = F.gelu(x).float()
        return F.linear(x, self.w2, self.b2).permute(0, 3, 1, 2).contiguous()
