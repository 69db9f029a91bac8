"""The RangeRet network prepared once for inference: the same function, a faster graph.

`FastGraph` is built from a loaded `RangeRet` in eval mode (`build_fast_graph`) and computes its
logits from the inference forms of its blocks (`rangeret.models.blocks.inference_stem` and
`inference_forms`): weights held in the compute dtype (converted once, so a bfloat16 pass runs
without autocast and without a cast per weight and call), BatchNorm folded or reduced to an
in-place affine map, convolutions with their activations in oneDNN's kernels on the CPU,
channels-last feature maps (the layout oneDNN's convolutions run fastest in: 3.8 times faster than
NCHW in bfloat16, 1.1 times in float32), one projection for queries, keys and values, and in
bfloat16 the decayed softmax through torch's fused attention kernel, its bias built once per grid
in the backbone's `GridCache` (shared with the network).

The network itself is left as it is: training, checkpoints and exports use it, and its state_dict
is the only one. In float32 the graph's logits equal the network's to float rounding; in bfloat16
the heavy parts (convolutions, projections, attention) run in bfloat16, the residual stream of the
backbone and the last Linear of the head in float32 (`FastEmbedding` and `FoldedHead` say why).
torch.compile is left out: fusing the graph's pointwise steps, its inductor kernels shortened a
pass by a tenth to a sixth at best, after 35 to 110 s of compilation per resolution and batch
size, and gained nothing end to end on a loaded machine (`benchmarks/bench_precision.py
--compile`).

`inference_graph` says which runs get one: bfloat16 runs on the CPU, where it is 3 times faster
than the network under autocast. Float32 runs keep the network as it is: the graph's float32 pass
is only 2 to 5 % faster (its convolutions already run at the core's peak), and its other rounding
can flip the class of a point whose two best logits are within float rounding of each other,
which the published pipeline's labels, equal on every point, do not allow. Float16 and bfloat16
on CUDA keep the network under autocast.
"""

from __future__ import annotations

import torch
from torch import nn

from rangeret.models.blocks.decay import GridCache
from rangeret.models.blocks.inference_forms import FastEmbedding, FastMixer, FoldedHead, fast_ffn
from rangeret.models.blocks.inference_stem import converted, fast_stem, fused_ops_available
from rangeret.models.network import RangeRet

#: Compute dtype of each precision name.
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}


class FastLayer(nn.Module):
    """One RetNet block (thesis Eq. 3.7): x + Mixer(LN1(x)), then + FFN(LN2(x)), with the
    residual stream x and the LayerNorms in float32 and the mixer and FFN in `dtype`
    (`FastEmbedding` says why)."""

    def __init__(
        self,
        mixer: nn.Module,
        ffn: nn.Module,
        norm1: nn.Module,
        norm2: nn.Module,
        dtype: torch.dtype,
    ) -> None:
        super().__init__()
        self.mixer, self.ffn = mixer, ffn
        self.norm1, self.norm2 = converted(norm1, torch.float32), converted(norm2, torch.float32)
        self.dtype = dtype

    def forward(self, x: torch.Tensor, grid: tuple[int, int], cache: GridCache) -> torch.Tensor:
        """Float32 (B, N, dim) -> float32 (B, N, dim)."""
        x = x + self.mixer(self.norm1(x).to(self.dtype), grid, cache)
        return x + self.ffn(self.norm2(x).to(self.dtype), grid)


class FastGraph(nn.Module):
    """(B, 5, H, W) float32 range image -> float32 (B, classes, H, W) logits of `network`,
    computed in `dtype`. `fused` (default: on a CPU with oneDNN) selects the CPU's fused kernels:
    oneDNN's convolutions with their activations, and the decayed softmax one grid row at a time
    in torch's fused attention kernel. Without them every step is a plain torch operation and the
    token mixers take the training blocks' choice of form, as on CUDA."""

    def __init__(
        self, network: RangeRet, dtype: torch.dtype = torch.float32, fused: bool | None = None
    ) -> None:
        super().__init__()
        device = next(network.parameters()).device
        fused = fused_ops_available(device) if fused is None else fused
        self.config = network.config
        self.dtype = dtype
        self.fused = fused
        self.rem, shift = fast_stem(network.rem, dtype, fused)
        self.viembed = FastEmbedding(network.viembed, dtype, fused, shift)
        backbone = network.backbone
        self.layers = nn.ModuleList(
            FastLayer(
                FastMixer(mixer, dtype, fused),
                fast_ffn(ffn, dtype, fused),
                norm1,
                norm2,
                dtype,
            )
            for mixer, ffn, norm1, norm2 in zip(
                backbone.retentions, backbone.ffns, backbone.norms1, backbone.norms2, strict=True
            )
        )
        self.head = FoldedHead(network.head, dtype, shift if network.config.residual else None)
        self._cache = [backbone.cache]  # shared with the network, so not a submodule of this one

    @property
    def cache(self) -> GridCache:
        """The network's `GridCache`, which this graph fills and reads too."""
        return self._cache[0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Float32 logits (B, C, H, W) of a (B, in_channels, H, W) batch."""
        if x.dim() != 4 or x.shape[1] != self.config.in_channels:
            raise ValueError(
                f"{self.config.name} takes (B, {self.config.in_channels}, H, W) input, got {tuple(x.shape)}"
            )
        features = self.rem(x.to(self.dtype, memory_format=torch.channels_last))
        tokens, grid = self.viembed(features)
        for layer in self.layers:
            tokens = layer(tokens, grid, self.cache)
        residual = features if self.config.residual else None
        tokens = tokens.to(self.dtype)
        return self.head(tokens, grid, (x.shape[-2], x.shape[-1]), residual)


@torch.no_grad()
def build_fast_graph(
    network: RangeRet, dtype: torch.dtype = torch.float32, fused: bool | None = None
) -> FastGraph:
    """The inference graph of a network in eval mode, on the network's device, in `dtype`."""
    if network.training:
        raise ValueError("an inference graph is built from a network in eval mode")
    return FastGraph(network, dtype, fused).eval()


def inference_graph(network: nn.Module, precision: str, device: torch.device) -> FastGraph | None:
    """The graph a torch-backend run at `precision` on `device` uses: bfloat16 on the CPU; None
    (the network runs as it is) for every other run and for a network that is not a `RangeRet`."""
    if not isinstance(network, RangeRet):
        return None
    if precision == "bf16" and device.type == "cpu":
        return build_fast_graph(network, DTYPES[precision])
    return None
