"""Inference forms of the released stem (REM): convolutions with their activations in the
kernel, and its BatchNorms as in-place affine maps or folded into a neighbouring convolution.

- `ConvAct`: a convolution with its activation (LeakyReLU, GELU) applied by the convolution
  kernel itself on the CPU (oneDNN post-ops), on channels-last feature maps, its weight stored
  channels-last too;
- `ChannelAffine`: an eval-mode BatchNorm as a per-channel affine map applied in place, in the
  compute dtype. Each BatchNorm of the stem follows a LeakyReLU (BN(LReLU(conv))), which is not
  linear, so it cannot be folded into the convolution before it; it is folded into the one after
  it where that convolution is unpadded (`shifted_input_bias`, and a3 into conv5 of
  `FastResidualBlock`), since a padded one reads zeros that no shift moves;
- `FastContextBlock`, `FastResidualBlock`, `fast_stem`: the released stem's blocks made of those.

`rangeret.models.blocks.inference_forms` holds the forms of the other blocks.
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from rangeret.models.blocks.stem import (
    LEAKY_SLOPE,
    ContextStem,
    ResidualBlock,
    ResidualContextBlock,
)

#: Activations a `ConvAct` applies: name -> (oneDNN post-op, its scalars).
ACTIVATIONS = {
    "none": ("none", []),
    "leaky_relu": ("leaky_relu", [LEAKY_SLOPE]),
    "gelu": ("gelu", []),
}


def fused_ops_available(device: torch.device) -> bool:
    """Whether the CPU's fused kernels run here: a CPU, with a torch built with oneDNN."""
    return (
        device.type == "cpu"
        and torch.backends.mkldnn.is_available()
        and hasattr(torch.ops.mkldnn, "_convolution_pointwise")
    )


def converted(module: nn.Module, dtype: torch.dtype) -> nn.Module:
    """A copy of `module` in eval mode with its floating-point weights in `dtype`."""
    return copy.deepcopy(module).to(dtype).eval()


def weight_buffer(tensor: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor | None:
    """A detached copy of a weight in `dtype` (None stays None)."""
    return None if tensor is None else tensor.detach().to(dtype).clone()


class ConvAct(nn.Module):
    """act(Conv2d(x)) with the activation applied by the convolution kernel where oneDNN runs
    (`fused`), else by a separate in-place pass. Output keeps the input's channels-last layout.
    `weight` and `bias` (float64) replace the convolution's own where something is folded in."""

    def __init__(
        self,
        conv: nn.Conv2d,
        act: str,
        dtype: torch.dtype,
        fused: bool,
        weight: torch.Tensor | None = None,
        bias: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        if act not in ACTIVATIONS:
            raise ValueError(f"unknown activation {act!r}; known: {', '.join(ACTIVATIONS)}")
        weight = weight_buffer(conv.weight if weight is None else weight, dtype)
        # channels-last like the feature maps, which oneDNN would otherwise copy it to per call
        self.register_buffer("weight", weight.contiguous(memory_format=torch.channels_last))
        self.register_buffer("bias", weight_buffer(conv.bias if bias is None else bias, dtype))
        self.stride = list(conv.stride)
        self.padding = list(conv.padding)
        self.dilation = list(conv.dilation)
        self.groups = conv.groups
        self.act = act
        self.fused = fused

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H', W')."""
        if self.fused:
            attr, scalars = ACTIVATIONS[self.act]
            algorithm = "none" if self.act == "gelu" else ""
            return torch.ops.mkldnn._convolution_pointwise(
                x,
                self.weight,
                self.bias,
                self.padding,
                self.stride,
                self.dilation,
                self.groups,
                attr,
                scalars,
                algorithm,
            )
        y = F.conv2d(
            x, self.weight, self.bias, self.stride, self.padding, self.dilation, self.groups
        )
        if self.act == "leaky_relu":
            return F.leaky_relu_(y, LEAKY_SLOPE)
        if self.act == "gelu":
            return F.gelu(y)
        return y


def shifted_input_bias(conv: nn.Conv2d, shift: torch.Tensor | None) -> torch.Tensor:
    """Float64 bias b' with conv(x + shift) = conv_b'(x) for a per-channel `shift` of the input.

    Exact only for a convolution without padding (every output reads only real pixels, each
    shifted); one with padding reads zeros that no shift moves, so it is refused.
    """
    bias = torch.zeros(conv.out_channels, dtype=torch.float64)
    if conv.bias is not None:
        bias = bias + conv.bias.detach().double().cpu()
    if shift is None:
        return bias.to(conv.weight.device)
    if any(conv.padding) or conv.groups != 1:
        raise ValueError("an input shift folds only into an unpadded, ungrouped convolution")
    weight = conv.weight.detach().double().cpu().sum((2, 3))
    return (bias + weight @ shift.cpu()).to(conv.weight.device)


class ChannelAffine(nn.Module):
    """An eval-mode BatchNorm2d as x * scale + shift per channel, written into x itself."""

    def __init__(self, bn: nn.BatchNorm2d, dtype: torch.dtype) -> None:
        super().__init__()
        scale, shift = batchnorm_affine(bn)
        self.register_buffer("scale", scale.to(dtype)[:, None, None])
        self.register_buffer("shift", shift.to(dtype)[:, None, None])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> the same tensor, normalised."""
        return torch.addcmul(self.shift, x, self.scale, out=x)


def batchnorm_affine(bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
    """(scale, shift) in float64 with BN(x) = x * scale + shift in eval mode."""
    weight = bn.weight.detach().double() if bn.affine else 1.0
    bias = bn.bias.detach().double() if bn.affine else 0.0
    scale = weight * torch.rsqrt(bn.running_var.double() + bn.eps)
    return scale, bias - bn.running_mean.double() * scale


class FastContextBlock(nn.Module):
    """`ResidualContextBlock`: s = LReLU(Conv1x1(x)); s + BN(LReLU(Conv3x3 d2(BN(LReLU(Conv3x3(s)))))).

    `input_shift` is the per-channel shift the previous block left out of x, folded into conv1
    (1 x 1, exact). With `pass_shift` this block leaves the shift of its last BatchNorm out in
    turn (`shift_out`), for consumers that fold it exactly: its output is then s + y * scale in
    one pass instead of two.
    """

    def __init__(
        self,
        block: ResidualContextBlock,
        dtype: torch.dtype,
        fused: bool,
        input_shift: torch.Tensor | None = None,
        pass_shift: bool = False,
    ) -> None:
        super().__init__()
        bias1 = shifted_input_bias(block.conv1, input_shift)
        self.conv1 = ConvAct(block.conv1, "leaky_relu", dtype, fused, bias=bias1)
        self.conv2 = ConvAct(block.conv2, "leaky_relu", dtype, fused)
        self.bn1 = ChannelAffine(block.bn1, dtype)
        self.conv3 = ConvAct(block.conv3, "leaky_relu", dtype, fused)
        self.bn2 = ChannelAffine(block.bn2, dtype)
        self.pass_shift = pass_shift
        self.shift_out = batchnorm_affine(block.bn2)[1] if pass_shift else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W), channels-last (less `shift_out`, if any)."""
        shortcut = self.conv1(x)
        a = self.bn1(self.conv2(shortcut))
        y = self.conv3(a)
        if self.pass_shift:
            return torch.addcmul(shortcut, y, self.bn2.scale, out=y)
        return self.bn2(y).add_(shortcut)


class FastResidualBlock(nn.Module):
    """`ResidualBlock`: LReLU(Conv1x1(x)) + BN(LReLU(Conv1x1(cat(a1, a2, a3)))), the a_i chained
    BN(LReLU(conv)) features of x.

    a3 is read by the 1 x 1 convolution alone, so its BatchNorm is folded into that convolution's
    weights; `pass_shift` leaves the last BatchNorm's shift out as `FastContextBlock` does.
    """

    def __init__(
        self, block: ResidualBlock, dtype: torch.dtype, fused: bool, pass_shift: bool = False
    ) -> None:
        super().__init__()
        self.conv1 = ConvAct(block.conv1, "leaky_relu", dtype, fused)
        self.conv2 = ConvAct(block.conv2, "leaky_relu", dtype, fused)
        self.bn1 = ChannelAffine(block.bn1, dtype)
        self.conv3 = ConvAct(block.conv3, "leaky_relu", dtype, fused)
        self.bn2 = ChannelAffine(block.bn2, dtype)
        self.conv4 = ConvAct(block.conv4, "leaky_relu", dtype, fused)
        width = block.conv4.out_channels
        scale3, shift3 = batchnorm_affine(block.bn3)
        weight5 = block.conv5.weight.detach().double().clone()
        bias5 = block.conv5.bias.detach().double() + weight5[:, -width:, 0, 0] @ shift3
        weight5[:, -width:] *= scale3[None, :, None, None]
        self.conv5 = ConvAct(block.conv5, "leaky_relu", dtype, fused, weight5, bias5)
        self.bn4 = ChannelAffine(block.bn4, dtype)
        self.pass_shift = pass_shift
        self.shift_out = batchnorm_affine(block.bn4)[1] if pass_shift else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W), channels-last (less `shift_out`, if any)."""
        shortcut = self.conv1(x)
        a1 = self.bn1(self.conv2(x))
        a2 = self.bn2(self.conv3(a1))
        a3 = self.conv4(a2)
        mixed = torch.cat((a1, a2, a3), dim=1)
        del a1, a2, a3
        y = self.conv5(mixed)
        if self.pass_shift:
            return torch.addcmul(shortcut, y, self.bn4.scale, out=y)
        return self.bn4(y).add_(shortcut)


def fast_stem(
    stem: nn.Module, dtype: torch.dtype, fused: bool
) -> tuple[nn.Module, torch.Tensor | None]:
    """The inference form of a REM, and the per-channel shift it leaves out of its output for
    its consumers to fold (None: the output is complete).

    The released stem's blocks pass the shift of their last BatchNorm on where every reader of
    their output folds it exactly: the next context block (whose 1 x 1 conv1 alone reads it) and,
    after the last block, the patch embedding (unpadded) and the head (a Linear). The residual
    block's 3 x 3 conv2 is padded, so the block before it keeps its shift. Other REMs are
    converted as they are.
    """
    if not isinstance(stem, ContextStem):
        return converted(stem, dtype), None
    blocks: list[nn.Module] = []
    shift = None
    parts = list(stem.conv_block)
    for i, block in enumerate(parts):
        following = parts[i + 1] if i + 1 < len(parts) else None
        pass_shift = following is None or isinstance(following, ResidualContextBlock)
        if isinstance(block, ResidualContextBlock):
            fast: nn.Module = FastContextBlock(block, dtype, fused, shift, pass_shift)
        elif isinstance(block, ResidualBlock) and shift is None:
            fast = FastResidualBlock(block, dtype, fused, pass_shift)
        else:
            raise TypeError(f"no inference form for {type(block).__name__} in this stem")
        shift = fast.shift_out
        blocks.append(fast)
    return nn.Sequential(*blocks), shift
