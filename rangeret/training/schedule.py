"""Optimiser and learning-rate schedules (thesis section 4.3, Algorithm 1).

AdamW (lr 1e-3, weight decay 0.05), stepped once per batch under one of two schedules over the
run's T steps. Both climb from `lr` to `max_lr` (1e-2) over the first `warmup` share of the steps
(0.3; the ablations of chapter 5 used 0.02), reach the peak at step round(warmup x T), and then
fall along a cosine to lr / 1e4 at the last step:

- `onecycle` (the thesis's 1cycle policy, as torch's OneCycleLR draws it): the climb is a cosine
  too, and AdamW's beta1 moves the other way, from 0.95 down to 0.85 at the peak and back up.
  The cycle starts at `lr` (torch's div_factor = max_lr / lr), so the optimiser's lr is the
  starting point rather than a value the schedule overrides.
- `cosine`: a linear warm-up, then the cosine; betas stay as AdamW sets them.

Unlike OneCycleLR, any number of steps from 1 up is valid (short test runs included).

A run names its optimiser (`OPTIMIZERS`) and schedule (`SCHEDULES`) in its `TrainConfig`; the
checkpoints record them under the names of `OPTIMIZERS` and `SCHEDULE_NAMES`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import torch

#: The optimisers a run may name, with the name its checkpoints record.
OPTIMIZERS = {"adamw": "AdamW"}
#: The schedules a run may name, with the name its checkpoints record.
SCHEDULE_NAMES = {"onecycle": "OneCycleLR", "cosine": "warmup-cosine"}
SCHEDULES = tuple(SCHEDULE_NAMES)
#: The schedules end at lr / FINAL_DIV (OneCycleLR's default final_div_factor).
FINAL_DIV = 1e4
#: beta1 of AdamW at the start and end (high) and at the peak of the learning rate (low), onecycle.
BETA1_RANGE = (0.95, 0.85)


def build_optimizer(
    parameters: Iterable[torch.nn.Parameter],
    lr: float = 1e-3,
    weight_decay: float = 0.05,
    name: str = "adamw",
) -> torch.optim.Optimizer:
    """The optimiser `name` of `OPTIMIZERS`. adamw is AdamW with the thesis's settings (betas
    0.9/0.999, eps 1e-8 as in Algorithm 1), fused: its step counters stay on the device and it
    takes the fp16 gradient scaler's overflow check there, so a step never waits for the device
    (torch < 2.4 has no fused CPU kernel)."""
    if name not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {name!r}; known: {', '.join(OPTIMIZERS)}")
    params = list(parameters)
    try:
        return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay, fused=True)
    except RuntimeError:
        return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict[str, Any]) -> None:
    """Load `state` into `optimizer`, keeping its own kernel choice (fused or not), so that a state
    saved by another implementation (the unfused AdamW of earlier runs) continues fused."""
    kernels = [{k: g[k] for k in ("fused", "foreach") if k in g} for g in optimizer.param_groups]
    groups = [{**saved, **own} for saved, own in zip(state["param_groups"], kernels, strict=True)]
    optimizer.load_state_dict({**state, "param_groups": groups})


def _cosine_step(start: float, end: float, progress: float) -> float:
    """From `start` at progress 0 to `end` at progress 1 along half a cosine."""
    return end + 0.5 * (start - end) * (1.0 + math.cos(math.pi * progress))


class CycleSchedule(torch.optim.lr_scheduler.LRScheduler):
    """The per-step schedule `shape` ("onecycle" or "cosine") over `total_steps` steps; see the
    module docstring. Its state (plain numbers) saves and loads like any torch scheduler's."""

    def __init__(
        self,
        optimizer: torch.optim.Optimizer,
        shape: str,
        total_steps: int,
        max_lr: float,
        warmup: float,
    ) -> None:
        if shape not in SCHEDULES:
            raise ValueError(f"unknown schedule {shape!r}; known: {', '.join(SCHEDULES)}")
        if total_steps < 1:
            raise ValueError(f"a schedule needs at least one step, got {total_steps}")
        if not 0.0 < warmup < 1.0:
            raise ValueError(f"the warm-up share must lie in (0, 1), got {warmup}")
        lr = optimizer.param_groups[0]["lr"]
        if max_lr < lr:
            raise ValueError(f"max_lr ({max_lr}) must not be below lr ({lr})")
        self.shape = shape
        self.total_steps = int(total_steps)
        self.warmup_steps = min(max(round(warmup * total_steps), 1), total_steps - 1)
        self.peak = max_lr / lr
        self.floor = 1.0 / FINAL_DIV
        super().__init__(optimizer)

    def factor(self, step: int) -> tuple[float, float]:
        """(multiplier of the base lr, progress from 0 at the start to 1 at the peak and back to 0)."""
        if step < self.warmup_steps:
            progress = step / self.warmup_steps
            if self.shape == "onecycle":
                return _cosine_step(1.0, self.peak, progress), 0.5 * (
                    1.0 - math.cos(math.pi * progress)
                )
            return 1.0 + (self.peak - 1.0) * progress, progress
        span = max(self.total_steps - 1 - self.warmup_steps, 1)
        progress = min((step - self.warmup_steps) / span, 1.0)
        return _cosine_step(self.peak, self.floor, progress), 0.5 * (
            1.0 + math.cos(math.pi * progress)
        )

    def get_lr(self) -> list[float]:
        """Learning rates of the current step (and, for onecycle, beta1 set on the groups)."""
        multiplier, height = self.factor(self.last_epoch)
        if self.shape == "onecycle":
            high, low = BETA1_RANGE
            for group in self.optimizer.param_groups:
                group["betas"] = (high + (low - high) * height, group["betas"][1])
        return [base * multiplier for base in self.base_lrs]


def build_scheduler(
    optimizer: torch.optim.Optimizer,
    kind: str,
    total_steps: int,
    max_lr: float = 1e-2,
    warmup: float = 0.3,
) -> CycleSchedule:
    """The per-step schedule `kind` ("onecycle" or "cosine") over `total_steps` optimiser steps."""
    return CycleSchedule(optimizer, kind, total_steps, max_lr, warmup)
