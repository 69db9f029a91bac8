"""The training loop: one process, or one rank of a data-parallel group (`distributed`).

`Trainer(config).fit()` trains a RangeRet network on a tree of the config's dataset profile
(its layout, point record, projection, labels and kNN rule) and writes, in `config.out`:

- `last.pt` and `best.pt`: the project's self-describing checkpoints (`rangeret.models.
  save_checkpoint`), loadable with `load_checkpoint(path)` alone. They record the profile with the
  projection actually used, so `rangeret predict` runs them with it. Their metadata records the epoch,
  the step, the epoch's metrics, the optimiser, schedule and losses, and the whole `TrainConfig`.
  best.pt is the epoch with the highest point mIoU after kNN on the validation scans (the
  benchmark's number), or the lowest training loss when there is no validation set.
- `last.state.pt`: what an exact resume needs beyond the weights (see `state.py`).
- `steps.csv`, `metrics.csv` and `curves.png` (see `logs.py`).

With `init_from` the run starts from a checkpoint's weights (`init_from.py`, `parent` in the
metadata); the metadata's `label_set` names the classes trained for.

Every epoch ends with validation (`validation.py`). The training step and the validation forward
run at the config's `precision` (`rangeret.inference.runtime.precision`; auto is bf16 where the
CPU or the CUDA device runs bf16 natively, fp32 elsewhere), with a gradient scaler for fp16 only.
The precision used is logged at the start, recorded in the checkpoints and the resume state, and
a resume at another precision is refused. A step reads back from the device once: its losses,
as one list (`Trainer.train_step`); confusion counts stay on the device until the epoch ends, and
the fused AdamW takes the fp16 scaler's overflow check on the device.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from rangeret.dataset.labels import LabelConfig
from rangeret.evaluation.metrics import ConfusionMatrix
from rangeret.inference.point_labels import pixel_classes
from rangeret.inference.runtime.device import select_device
from rangeret.inference.runtime.precision import forward_precision, resolve_precision
from rangeret.inference.settings import KnnSettings
from rangeret.models import RangeRet, build_model, save_checkpoint
from rangeret.training.config import TrainConfig
from rangeret.training.data import (
    EpochSampler,
    RangeDataset,
    collate,
    run_datasets,
    steps_per_epoch,
    training_profile,
)
from rangeret.training.distributed import Ranks, wrap_for_ranks
from rangeret.training.init_from import FineTuning, settle_run
from rangeret.training.logs import CsvLog, metrics_columns, plot_curves
from rangeret.training.losses import SegmentationLoss, class_weights
from rangeret.training.schedule import build_optimizer, build_scheduler, load_optimizer_state
from rangeret.training.state import (
    BEST,
    CURVES_PNG,
    LAST,
    METRICS_CSV,
    STATE,
    STATE_FORMAT,
    STATE_VERSION,
    STEPS_CSV,
    better_epoch,
    check_run_folder,
    label_set,
    read_state,
    rng_state,
    run_record,
    save_atomic,
    seed_everything,
    set_rng_state,
)
from rangeret.training.validation import VAL_METRICS, confusion_matrix, validate

log = logging.getLogger("rangeret.training")


@dataclass
class TrainResult:
    """What a run did: per-step losses, per-epoch rows, the best epoch, and its output folder."""

    out: Path
    steps: list[dict[str, float]] = field(default_factory=list)
    epochs: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, Any] | None = None


class Trainer:
    """Trains one network as `config` says; see the module docstring for what it writes.

    `label_config` replaces the profile's labels; `device` overrides `config.device` (a
    data-parallel worker passes its own); `on_epoch_end` is called on every rank with each epoch's
    metrics (Ray Train reports them through it).
    """

    def __init__(
        self,
        config: TrainConfig,
        *,
        label_config: LabelConfig | None = None,
        device: str | torch.device | None = None,
        on_epoch_end: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        self.out = Path(config.out)
        self.device = select_device(device if device is not None else config.device)
        if self.device.type == "cuda" and self.device.index is None:
            self.device = torch.device("cuda", torch.cuda.current_device())
        self.precision = resolve_precision(config.precision, self.device)
        config = dataclasses.replace(config, precision=self.precision)
        self.ranks = Ranks.detect(self.device)
        self.on_epoch_end = on_epoch_end
        self.profile = training_profile(config, label_config)
        config, parent = settle_run(config, self.profile)
        self.config = config
        self.label_config = self.profile.labels
        self.projection = self.profile.projection
        self.num_classes = self.profile.num_classes
        self.unlabeled = self.label_config.unlabeled_class
        self.ignored = [c for c in range(self.num_classes) if self.label_config.ignored[c]]
        self.knn = KnnSettings()

        state_path = check_run_folder(self.out, config.resume)
        state = read_state(state_path, config, self.profile) if config.resume else None

        seed_everything(config.seed)
        data = run_datasets(config, self.profile)
        self.frequencies = data.frequencies
        self.train_set, self.val_set = data.train, data.valid

        self.model: RangeRet = build_model(
            config.model,
            self.projection.height,
            self.projection.width,
            self.num_classes,
            **config.overrides,
        ).to(self.device)
        self.tuning = FineTuning.start(parent, self.model, config, announce=self.ranks.main)
        weights = class_weights(self.frequencies, self.label_config.ignored, config.class_weighting)
        self.criterion = SegmentationLoss(
            config.losses, weights, config.focal_gamma, ignore_index=self.unlabeled
        ).to(self.device)
        self.optimizer = build_optimizer(
            self.model.parameters(), config.lr, config.weight_decay, config.optimizer
        )
        self.steps_per_epoch = steps_per_epoch(
            len(self.train_set), config.batch_size, self.ranks.world_size
        )
        planned = config.epochs * self.steps_per_epoch
        self.total_steps = min(planned, config.max_steps) if config.max_steps else planned
        self.num_epochs = -(-self.total_steps // self.steps_per_epoch)
        self.scheduler = build_scheduler(
            self.optimizer, config.schedule, self.total_steps, config.max_lr, config.warmup
        )
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.precision == "fp16")

        self.step = 0
        self.best: dict[str, Any] | None = None
        self._reset_epoch_totals()
        if state is not None:
            self._restore(state_path, state)

        self.network = wrap_for_ranks(self.model, self.ranks, self.device)
        self.loss_names = ("loss", *self.criterion.losses)
        self.steps_log = CsvLog(self.out / STEPS_CSV, ["step", "epoch", *self.loss_names, "lr"])
        columns = metrics_columns(self.criterion.losses, VAL_METRICS)
        self.metrics_log = CsvLog(self.out / METRICS_CSV, columns)
        self._pending_steps: list[dict[str, float]] = []
        self._pending_epochs: list[dict[str, Any]] = []
        self.result = TrainResult(self.out)

    def _reset_epoch_totals(self) -> None:
        self.epoch_loss = torch.zeros(1 + len(self.criterion.losses), dtype=torch.float64)
        self.epoch_batches = 0
        self.epoch_confusion = torch.zeros(
            self.num_classes * self.num_classes, dtype=torch.int64, device=self.device
        )
        self.epoch_started = time.perf_counter()
        self.epoch_seconds = 0.0

    # Training ------------------------------------------------------------------------------

    def fit(self, until_step: int | None = None) -> TrainResult:
        """Train until the planned number of steps (or `until_step`, saving the state there)."""
        if self.ranks.main:
            self.out.mkdir(parents=True, exist_ok=True)
            keep = self.step if self.config.resume else None
            self.steps_log.start(keep)
            self.metrics_log.start(keep)
        self.ranks.barrier()
        stop = self.total_steps if until_step is None else min(until_step, self.total_steps)
        log.info(
            "%s (%s profile) at %dx%d: %d training and %d validation scans, %d steps per epoch, "
            "%d steps (%s) on %s x %d in %s%s",
            self.config.model,
            self.profile.name,
            self.projection.height,
            self.projection.width,
            len(self.train_set),
            len(self.val_set),
            self.steps_per_epoch,
            self.total_steps,
            f"{self.num_epochs} epoch{'' if self.num_epochs == 1 else 's'}",
            self.device,
            self.ranks.world_size,
            self.precision,
            f", resumed at step {self.step}" if self.step else "",
        )
        while self.step < stop:
            epoch = self.step // self.steps_per_epoch
            epoch_end = min((epoch + 1) * self.steps_per_epoch, self.total_steps)
            self._train_epoch(epoch, min(epoch_end, stop))
            if self.step == epoch_end:
                self._end_epoch(epoch)
            else:
                self._save(epoch, complete=False, metrics=None)
        return self.result

    def _train_epoch(self, epoch: int, stop: int) -> None:
        """Steps of `epoch` from the current step up to step `stop`."""
        offset = self.step - epoch * self.steps_per_epoch
        sampler = EpochSampler(
            len(self.train_set),
            epoch,
            self.config.seed,
            batch_size=self.config.batch_size,
            rank=self.ranks.rank,
            world_size=self.ranks.world_size,
            start=offset,
        )
        loader = self._loader(self.train_set, sampler)
        span = (
            min(self.total_steps, (epoch + 1) * self.steps_per_epoch) - epoch * self.steps_per_epoch
        )
        bar = tqdm(
            total=span,
            initial=offset,
            desc=f"epoch {epoch + 1}/{self.num_epochs}",
            unit="step",
            disable=not (self.config.progress and self.ranks.main),
            leave=False,
        )
        self.epoch_started = time.perf_counter()
        try:
            for batch in loader:
                if self.step >= stop:
                    break
                lr = self.optimizer.param_groups[0]["lr"]
                values = self.train_step(batch)
                row = {
                    "step": self.step,
                    "epoch": epoch + 1,
                    "lr": lr,
                    **dict(zip(self.loss_names, values, strict=True)),
                }
                self._pending_steps.append(row)
                self.result.steps.append(row)
                bar.update(1)
                bar.set_postfix(loss=f"{values[0]:.4f}", lr=f"{lr:.2e}")
                if (
                    self.config.checkpoint_every
                    and self.step % self.config.checkpoint_every == 0
                    and self.step < stop
                ):
                    self._save(epoch, complete=False, metrics=None)
        finally:
            bar.close()
        self.epoch_seconds += time.perf_counter() - self.epoch_started

    def train_step(self, batch: Mapping[str, Any]) -> list[float]:
        """One optimiser step on a batch; returns [total loss, *terms] averaged over ranks.

        That list is the step's one read-back from the device (`.tolist()` of the stacked terms);
        nothing else in the step waits for the device.
        """
        self.network.train()
        self.tuning.hold(self.step)
        images = batch["image"].to(self.device, non_blocking=True)
        labels = batch["label"].to(self.device, non_blocking=True)
        with forward_precision(self.precision, self.device):
            logits = self.network(images)
        loss, terms = self.criterion(logits, labels)
        self.optimizer.zero_grad(set_to_none=True)
        with self._backward_precision():
            self.scaler.scale(loss).backward()
        self.tuning.drop_gradients(self.step)
        if self.config.clip_grad > 0:
            self.scaler.unscale_(self.optimizer)
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.clip_grad)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        self.step += 1
        with torch.no_grad():
            pred = pixel_classes(logits.detach())
            cells = (pred * self.num_classes + labels).reshape(-1)
            self.epoch_confusion.index_add_(0, cells, torch.ones_like(cells))
            values = torch.stack([loss.detach(), *(t.detach() for t in terms.values())]).double()
        means = self.ranks.mean_to_host(values)
        self.epoch_loss += torch.tensor(means, dtype=torch.float64)
        self.epoch_batches += 1
        return means

    def _backward_precision(self) -> contextlib.AbstractContextManager[None]:
        """fp32's setting (TF32 off on CUDA) for the backward pass too; under autocast the
        backward pass follows the forward pass's dtypes by itself."""
        if self.precision == "fp32":
            return forward_precision("fp32", self.device)
        return contextlib.nullcontext()

    def _loader(self, dataset: RangeDataset, sampler: EpochSampler) -> DataLoader:
        """Batches of `sampler`'s keys. The loader's own generator (it seeds its worker processes)
        is a local one, so creating a loader leaves the global random state alone."""
        return DataLoader(
            dataset,
            batch_size=self.config.batch_size,
            sampler=sampler,
            collate_fn=collate,
            num_workers=self.config.loader_workers,
            pin_memory=self.device.type == "cuda",
            generator=torch.Generator().manual_seed(self.config.seed),
        )

    # Epoch ends, validation ------------------------------------------------------------------

    def _end_epoch(self, epoch: int) -> None:
        """Validate, log the epoch, save last.pt (and best.pt when it improved) and the state."""
        train = self.epoch_loss / max(self.epoch_batches, 1)
        confusion = self.ranks.sum(self.epoch_confusion)
        cm = self._matrix(confusion)
        metrics: dict[str, Any] = {
            "epoch": epoch + 1,
            "step": self.step,
            "lr": self.optimizer.param_groups[0]["lr"],
            "train_loss": float(train[0]),
            **{
                f"train_{n}": float(v)
                for n, v in zip(self.criterion.losses, train[1:], strict=True)
            },
            "train_miou_image": cm.miou(),
        }
        if len(self.val_set):
            metrics.update(self.validate())
        metrics["seconds"] = self.epoch_seconds
        self._pending_epochs.append(metrics)
        self.result.epochs.append(metrics)
        if self.ranks.main:
            text = ", ".join(
                f"{k} {v:.4f}" for k, v in metrics.items() if k.startswith(("train_loss", "val_"))
            )
            log.info("epoch %d/%d (step %d): %s", epoch + 1, self.num_epochs, self.step, text)
        self._save(epoch, complete=True, metrics=metrics)
        if self.on_epoch_end is not None:
            self.on_epoch_end(dict(metrics))

    def _matrix(self, flat: torch.Tensor) -> ConfusionMatrix:
        """A ConfusionMatrix of the label configuration from flat C[pred, gt] counts."""
        return confusion_matrix(flat, self.label_config)

    def validate(self) -> dict[str, float]:
        """Loss and mIoU / accuracy on the validation scans: range image, points, points + kNN."""
        sampler = EpochSampler(
            len(self.val_set),
            0,
            self.config.seed,
            batch_size=self.config.batch_size,
            rank=self.ranks.rank,
            world_size=self.ranks.world_size,
            shuffle=False,
            pad=False,
        )
        bar = tqdm(
            total=len(sampler),
            desc="validation",
            unit="scan",
            leave=False,
            disable=not (self.config.progress and self.ranks.main),
        )
        try:
            return validate(
                self.model,
                self.criterion,
                self._loader(self.val_set, sampler),
                profile=self.profile,
                knn=self.knn,
                precision=self.precision,
                device=self.device,
                ranks=self.ranks,
                progress=bar,
            )
        finally:
            bar.close()

    # Saving and resuming ---------------------------------------------------------------------

    def _improved(self, metrics: Mapping[str, Any]) -> bool:
        """Whether `metrics` beat the best epoch so far (and record them as the best if so)."""
        best = better_epoch(self.best, metrics)
        if best is not None:
            self.best = best
        return best is not None

    def _metadata(
        self, epoch: int, complete: bool, metrics: Mapping[str, Any] | None
    ) -> dict[str, Any]:
        return {
            "epoch": epoch + 1,
            "epoch_complete": complete,
            "step": self.step,
            "total_steps": self.total_steps,
            "metrics": dict(metrics) if metrics else None,
            "best": dict(self.best) if self.best else None,
            "label_set": label_set(self.profile),
            "parent": self.tuning.record(),
            **run_record(
                self.config,
                losses=self.criterion.losses,
                world_size=self.ranks.world_size,
                train_scans=len(self.train_set),
                val_scans=len(self.val_set),
            ),
        }

    def _save(self, epoch: int, complete: bool, metrics: Mapping[str, Any] | None) -> None:
        """Append the logs, write the resume state and last.pt, best.pt when it improved (rank 0)."""
        improved = complete and metrics is not None and self._improved(metrics)
        if self.ranks.main:
            self.steps_log.append(self._pending_steps)
            self.metrics_log.append(self._pending_epochs)
            state = {
                "format": STATE_FORMAT,
                "format_version": STATE_VERSION,
                "config": self.config.to_dict(),
                "profile": self.profile.to_dict(),
                "model": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
                "optimizer": self.optimizer.state_dict(),
                "scheduler": self.scheduler.state_dict(),
                "scaler": self.scaler.state_dict(),
                "step": self.step,
                "best": self.best,
                "epoch_totals": self._epoch_totals(complete),
                "parent": self.tuning.record(),
                "rng": rng_state(),
            }
            save_atomic(state, self.out / STATE)
            records = {
                "label_config": self.label_config.to_dict(),
                "projection": self.projection.to_dict(),
                "metadata": self._metadata(epoch, complete, metrics),
                "profile": self.profile.to_dict(),
            }
            save_checkpoint(self.out / LAST, self.model, **records)
            if improved:
                save_checkpoint(self.out / BEST, self.model, **records)
            if complete:
                plot_curves(self.out / STEPS_CSV, self.out / METRICS_CSV, self.out / CURVES_PNG)
        self._pending_steps = []
        self._pending_epochs = []
        if complete:
            self._reset_epoch_totals()
        self.result.best = dict(self.best) if self.best else None
        self.ranks.barrier()

    def _epoch_totals(self, complete: bool) -> dict[str, Any]:
        """Running sums of the current epoch (empty at an epoch's end)."""
        if complete:
            return {}
        return {
            "loss": self.epoch_loss.clone(),
            "batches": self.epoch_batches,
            "confusion": self.epoch_confusion.cpu().clone(),
            "seconds": self.epoch_seconds,
        }

    def _restore(self, path: Path, state: Mapping[str, Any]) -> None:
        """Restore everything `_save` wrote, from the state `read_state` checked."""
        self.tuning.check_resume(path, state)
        self.model.load_state_dict(state["model"])
        load_optimizer_state(self.optimizer, state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if state["scaler"]:
            self.scaler.load_state_dict(state["scaler"])
        self.step = int(state["step"])
        self.best = state["best"]
        totals = state["epoch_totals"]
        if totals:
            self.epoch_loss = totals["loss"].clone()
            self.epoch_batches = int(totals["batches"])
            self.epoch_confusion = totals["confusion"].to(self.device, copy=True)
            self.epoch_seconds = float(totals["seconds"])
        set_rng_state(state["rng"])
        log.info("resumed from %s at step %d", path, self.step)
