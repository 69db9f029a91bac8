"""Data-parallel ranks under torch.distributed, and what DistributedDataParallel must be told.

When torch.distributed is initialised (by Ray Train's TorchTrainer or torchrun) the trainer
wraps the network in DistributedDataParallel, each rank trains on its share of every epoch,
validation confusion matrices are summed across ranks (`Ranks.sum`), and rank 0 writes the
files. Parameters that take no part in the loss (the released network's `g_proj`) are found by
one small dry run and logged; DDP is told to look for unused parameters (`find_unused_parameters`,
a graph walk every step) only when there are some (`ddp_find_unused`).
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

log = logging.getLogger("rangeret.training")


@dataclass(frozen=True)
class Ranks:
    """This process's place in a data-parallel group (rank 0 of 1 when running alone), and the
    device its collectives run on (the GPU under NCCL, the CPU under gloo)."""

    rank: int = 0
    world_size: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @classmethod
    def detect(cls, device: torch.device) -> Ranks:
        """The torch.distributed group's rank and size, when one is initialised."""
        if dist.is_available() and dist.is_initialized():
            nccl = dist.get_backend() == "nccl"
            return cls(
                dist.get_rank(), dist.get_world_size(), device if nccl else torch.device("cpu")
            )
        return cls()

    @property
    def main(self) -> bool:
        """True on the rank that writes files and shows progress."""
        return self.rank == 0

    def sum(self, tensor: torch.Tensor) -> torch.Tensor:
        """`tensor` summed over all ranks (a new tensor on the input's device)."""
        if self.world_size == 1:
            return tensor
        work = tensor.to(self.device, copy=True)
        dist.all_reduce(work, op=dist.ReduceOp.SUM)
        return work.to(tensor.device)

    def mean_to_host(self, tensor: torch.Tensor) -> list[float]:
        """`tensor` averaged over all ranks, read back to the host in one transfer."""
        if self.world_size == 1:
            return tensor.tolist()
        work = tensor.to(self.device, copy=True)
        dist.all_reduce(work, op=dist.ReduceOp.SUM)
        return (work / self.world_size).tolist()

    def barrier(self) -> None:
        """Wait for every rank."""
        if self.world_size > 1:
            ids = [self.device.index] if self.device.type == "cuda" else None
            dist.barrier(device_ids=ids)


def unused_parameters(model: torch.nn.Module) -> list[str]:
    """Names of parameters that get no gradient from the output (found on a copy, smallest input).

    The input is one patch, so the patch grid is 1 x 1; the copy runs in eval mode so nothing of
    the original changes, and the generator is a local one so the global random state is kept.
    """
    probe = copy.deepcopy(model).eval()
    config = probe.config
    size = (1, config.in_channels, config.patch_size[0], config.patch_size[1])
    device = next(probe.parameters()).device
    x = torch.randn(size, generator=torch.Generator().manual_seed(0)).to(device)
    probe(x).float().square().mean().backward()
    return [name for name, p in probe.named_parameters() if p.requires_grad and p.grad is None]


def ddp_find_unused(model: torch.nn.Module) -> bool:
    """Whether DDP must look for unused parameters (`find_unused_parameters`): only when
    `unused_parameters` finds some, since the search walks the autograd graph every step."""
    unused = unused_parameters(model)
    if unused:
        log.info(
            "%d parameters take no part in the loss, DDP will look for unused parameters: %s",
            len(unused),
            ", ".join(unused),
        )
    else:
        log.info("every parameter takes part in the loss: DDP runs without find_unused_parameters")
    return bool(unused)


def wrap_for_ranks(model: torch.nn.Module, ranks: Ranks, device: torch.device) -> torch.nn.Module:
    """`model` itself when running alone, else wrapped in DistributedDataParallel on `device`."""
    if ranks.world_size == 1:
        return model
    return DistributedDataParallel(
        model,
        device_ids=[device.index] if device.type == "cuda" else None,
        find_unused_parameters=ddp_find_unused(model),
    )
