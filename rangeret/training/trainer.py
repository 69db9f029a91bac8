"""The training loop: one process, or one rank of a data-parallel group (torch.distributed).

`Trainer(config).fit()` trains a RangeRet network on a tree of the config's dataset profile
(its layout, point record, projection, labels and kNN rule) and writes, in `config.out`:

- `last.pt` and `best.pt`: the project's self-describing checkpoints (`rangeret.models.
  save_checkpoint`), loadable with `load_checkpoint(path)` alone. They record the profile with the
  projection actually used, so `rangeret predict` runs them with it. Their metadata records the epoch,
  the step, the epoch's metrics, the optimiser, schedule and losses, and the whole `TrainConfig`.
  best.pt is the epoch with the highest point mIoU after kNN on the validation scans (the
  benchmark's number), or the lowest training loss when there is no validation set.
- `last.state.pt`: what an exact resume needs beyond the weights: the model, optimiser, scheduler
  and gradient-scaler states, epoch, step, the running sums of the current epoch and the random
  states of python, numpy and torch. It is plain data and tensors (loads with weights_only=True).
- `steps.csv`, `metrics.csv` and `curves.png` (see `logs.py`).

Every epoch ends with validation: the loss, and mIoU / accuracy on the range image (labelled
pixels), on the points (each point takes its pixel's class) and on the points after kNN refinement
with the profile's voting rule (`rangeret.inference.point_labels.point_classes`), with the official
semantics of `rangeret.evaluation.metrics`.

The training step and the validation forward run at the config's `precision`
(`rangeret.inference.runtime.precision`; auto is fp16 on CUDA, fp32 on the CPU), with a gradient scaler for fp16
only. The precision used is logged at the start, recorded in the checkpoints and the resume
state, and a resume at another precision is refused. A step reads back from the device once: its
losses, as one list (`Trainer.train_step`); confusion counts stay on the device until the epoch
ends, and the fused AdamW takes the fp16 scaler's overflow check on the device.

When torch.distributed is initialised (by Ray Train's TorchTrainer or torchrun) the network is
wrapped in DistributedDataParallel, each rank trains on its share of every epoch, validation
confusion matrices are summed across ranks, and rank 0 writes the files. Parameters that take no
part in the loss (the released network's `g_proj`) are found by one small dry run and logged; DDP
is told to look for unused parameters (`find_unused_parameters`, a graph walk every step) only
when there are some (`ddp_find_unused`).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import logging
import random
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader
from tqdm import tqdm

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.layout import DatasetLayoutError, ScanEntry, discover, resolve_sequences
from rangeret.dataset.profiles import DatasetProfile, ProfileError, profile_of_record
from rangeret.evaluation.metrics import ConfusionMatrix
from rangeret.exceptions import InputError
from rangeret.inference.point_labels import point_classes
from rangeret.inference.runtime.device import select_device
from rangeret.inference.runtime.precision import forward_precision, resolve_precision
from rangeret.inference.settings import KnnSettings
from rangeret.io.atomic import atomic_path
from rangeret.models import RangeRet, build_model, save_checkpoint
from rangeret.training.config import TrainConfig
from rangeret.training.data import EpochSampler, RangeDataset, collate, steps_per_epoch
from rangeret.training.logs import CsvLog, plot_curves
from rangeret.training.losses import SegmentationLoss, class_weights
from rangeret.training.range_mixes import MixSettings, rare_classes
from rangeret.training.schedule import build_optimizer, build_scheduler, load_optimizer_state

log = logging.getLogger("rangeret.training")

LAST = "last.pt"
BEST = "best.pt"
STATE = "last.state.pt"
STEPS_CSV = "steps.csv"
METRICS_CSV = "metrics.csv"
CURVES_PNG = "curves.png"
STATE_FORMAT = "rangeret-train-state"
STATE_VERSION = 1
VAL_METRICS = (
    "val_loss",
    "val_miou_image",
    "val_acc_image",
    "val_miou_points",
    "val_acc_points",
    "val_miou_knn",
    "val_acc_knn",
)


class TrainingStateError(InputError, ValueError):
    """A training state that cannot be resumed, or an output folder that already holds a run."""


class TrainingStateMissing(InputError, FileNotFoundError):
    """--resume names an output folder without a training state."""


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


@dataclass
class TrainResult:
    """What a run did: per-step losses, per-epoch rows, the best epoch, and its output folder."""

    out: Path
    steps: list[dict[str, float]] = field(default_factory=list)
    epochs: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, Any] | None = None


def seed_everything(seed: int) -> None:
    """Seed python's, numpy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed % (1 << 32))
    torch.manual_seed(seed)


def rng_state() -> dict[str, Any]:
    """The global random states of python, numpy and torch (and CUDA), as plain data and tensors."""
    version, internal, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state: dict[str, Any] = {
        "python": [version, list(internal), gauss],
        "numpy": [name, keys.tolist(), int(pos), int(has_gauss), float(cached)],
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restore what `rng_state` returned."""
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


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


def save_atomic(payload: Any, path: Path) -> None:
    """torch.save `payload` to `path` atomically."""
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def training_profile(
    config: TrainConfig, label_config: LabelConfig | None = None
) -> DatasetProfile:
    """The profile `config` trains with (`label_config` in place of its labels when given),
    checked to read back from the plain data that the checkpoints will record."""
    profile = config.dataset_profile(label_config)
    try:
        profile_of_record(profile.to_dict(), profile.name)
    except ProfileError as exc:
        raise ProfileError(
            f"the {profile.name} profile with these options cannot be recorded in a checkpoint: {exc}"
        ) from exc
    return profile


def find_scans(
    root: Path | str, sequences: Sequence[str] | None, split: str, profile: DatasetProfile
) -> list[ScanEntry]:
    """The labelled scans of `sequences` (or of the profile's `split`) under `root`, in the
    profile's layout (ids normalised by it: "1" is "001" for PandaSet).

    Every missing folder, scan or label is reported in one DatasetLayoutError: training never runs
    on a silent subset.
    """
    if sequences is not None and len(sequences) == 0:
        return []
    layout = profile.layout
    names = (
        resolve_sequences(sequences=sequences, config=profile.labels, layout=layout)
        if sequences is not None
        else [layout.normalise(s) for s in resolve_sequences(split=split, config=profile.labels)]
    )
    found = discover(root, names, with_labels=True, layout=layout)
    if found.problems:
        hint = (
            ""
            if sequences is not None
            else f" (the {split!r} split; choose sequences with --{split.replace('valid', 'val')}-sequences)"
        )
        raise DatasetLayoutError(
            f"{len(found.problems)} problem(s) with the {split} data under {root}{hint}: "
            + "; ".join(found.problems[:5])
            + (" ..." if len(found.problems) > 5 else "")
        )
    return found.scans


def read_state(path: Path, config: TrainConfig, profile: DatasetProfile) -> dict[str, Any]:
    """The resume state at `path`, checked against the run that continues it: same profile
    (states from before profiles were SemanticKITTI's) and same settings but `RUNTIME_FIELDS`.

    The precision is compared as resolved (the trainer records fp16, fp32 or bf16); `auto` on
    either side (a state from before precisions were recorded, or a launcher that does not know
    its workers' device) is left to the check where both are known.
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise TrainingStateError(f"{path} cannot be read as a training state: {exc}") from exc
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise TrainingStateError(f"{path} is not a training state written by rangeret.training")
    if state.get("format_version") != STATE_VERSION:
        raise TrainingStateError(
            f"{path} has state version {state.get('format_version')!r}; this code reads {STATE_VERSION}"
        )
    stored = TrainConfig.from_dict(state["config"])
    recorded = profile_of_record(state.get("profile"), str(path))
    if recorded.name != profile.name:
        raise TrainingStateError(
            f"cannot resume {path}: the run was started with the {recorded.name} profile and "
            f"cannot continue with the {profile.name} profile (pass --profile {stored.profile})"
        )
    if "auto" in (stored.precision, config.precision):
        config = dataclasses.replace(config, precision=stored.precision)
    changed = stored.with_projection(recorded.projection).differences(
        config.with_projection(profile.projection)
    )
    if not changed and "profile" in state and recorded.to_dict() != profile.to_dict():
        changed = [f"the {recorded.name} profile's contents changed"]
    if changed:
        raise TrainingStateError(
            f"cannot resume {path}: the run was started with other settings ({'; '.join(changed)})"
        )
    return state


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
        self.config = config
        self.ranks = Ranks.detect(self.device)
        self.on_epoch_end = on_epoch_end
        self.profile = training_profile(config, label_config)
        self.label_config = self.profile.labels
        self.projection = self.profile.projection
        self.num_classes = self.profile.num_classes
        self.unlabeled = self.label_config.unlabeled_class
        self.ignored = [c for c in range(self.num_classes) if self.label_config.ignored[c]]
        self.knn = KnnSettings()

        state_path = self.out / STATE
        if config.resume and not state_path.exists():
            raise TrainingStateMissing(f"cannot resume: {state_path} does not exist")
        if not config.resume and state_path.exists():
            raise TrainingStateError(
                f"{self.out} already holds a training run ({STATE}): pass --resume to continue it, or choose another folder"
            )
        state = read_state(state_path, config, self.profile) if config.resume else None

        seed_everything(config.seed)
        train_scans = find_scans(config.dataset, config.train_sequences, "train", self.profile)
        val_scans = find_scans(config.dataset, config.val_sequences, "valid", self.profile)
        if not train_scans:
            raise DatasetLayoutError(f"no labelled training scan under {config.dataset}")
        self.frequencies = self._frequencies(train_scans)
        mixing = None
        if config.mixes:
            paste = rare_classes(self.frequencies, self.label_config.ignored)
            mixing = MixSettings(tuple(config.mixes), config.mix_probability, paste)
        common = {
            "projection": self.projection,
            "label_config": self.label_config,
            "seed": config.seed,
            "points": self.profile.points,
        }
        self.train_set = RangeDataset(train_scans, augment=config.augment, mixing=mixing, **common)
        self.val_set = RangeDataset(val_scans, with_points=True, **common)

        self.model: RangeRet = build_model(
            config.model,
            self.projection.height,
            self.projection.width,
            self.num_classes,
            **config.overrides,
        ).to(self.device)
        weights = class_weights(self.frequencies, self.label_config.ignored, config.class_weighting)
        self.criterion = SegmentationLoss(
            config.losses, weights, config.focal_gamma, ignore_index=self.unlabeled
        ).to(self.device)
        self.optimizer = build_optimizer(self.model.parameters(), config.lr, config.weight_decay)
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

        self.network: torch.nn.Module = self.model
        if self.ranks.world_size > 1:
            self.network = DistributedDataParallel(
                self.model,
                device_ids=[self.device.index] if self.device.type == "cuda" else None,
                find_unused_parameters=ddp_find_unused(self.model),
            )
        self.loss_names = ("loss", *self.criterion.losses)
        self.steps_log = CsvLog(self.out / STEPS_CSV, ["step", "epoch", *self.loss_names, "lr"])
        self.metrics_log = CsvLog(
            self.out / METRICS_CSV,
            [
                "epoch",
                "step",
                "lr",
                "seconds",
                "train_loss",
                *(f"train_{n}" for n in self.criterion.losses),
                "train_miou_image",
                *VAL_METRICS,
            ],
        )
        self._pending_steps: list[dict[str, float]] = []
        self._pending_epochs: list[dict[str, Any]] = []
        self.result = TrainResult(self.out)

    # Setup ---------------------------------------------------------------------------------

    def _frequencies(self, scans: Sequence[ScanEntry]) -> np.ndarray:
        """Shares of points per class: the label configuration's, or counted over the training
        labels when the configuration has none (data from another sensor)."""
        freq = self.label_config.class_frequencies()
        evaluated = [c for c in range(self.num_classes) if c not in self.ignored]
        if freq[evaluated].sum() > 0:
            return freq
        log.info("the label configuration has no class frequencies: counting the training labels")
        counts = RangeDataset(
            scans, self.projection, self.label_config, points=self.profile.points
        ).class_counts()
        return counts / max(counts.sum(), 1)

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
            "%d steps (%d epochs) on %s x %d in %s%s",
            self.config.model,
            self.profile.name,
            self.projection.height,
            self.projection.width,
            len(self.train_set),
            len(self.val_set),
            self.steps_per_epoch,
            self.total_steps,
            self.num_epochs,
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
        images = batch["image"].to(self.device, non_blocking=True)
        labels = batch["label"].to(self.device, non_blocking=True)
        with forward_precision(self.precision, self.device):
            logits = self.network(images)
        loss, terms = self.criterion(logits, labels)
        self.optimizer.zero_grad(set_to_none=True)
        with self._backward_precision():
            self.scaler.scale(loss).backward()
        if self.config.clip_grad > 0:
            self.scaler.unscale_(self.optimizer)
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.clip_grad)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        self.step += 1
        with torch.no_grad():
            pred = logits.detach().argmax(dim=1)
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
        cm = ConfusionMatrix.for_config(self.label_config)
        cm.merge(flat.reshape(self.num_classes, self.num_classes).cpu().numpy())
        return cm

    @torch.inference_mode()
    def validate(self) -> dict[str, float]:
        """Loss and mIoU / accuracy on the validation scans: range image, points, points + kNN."""
        self.model.eval()
        c = self.num_classes
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
        counts = torch.zeros(3, c * c, dtype=torch.int64, device=self.device)
        loss_sum = torch.zeros(2, dtype=torch.float64, device=self.device)
        bar = tqdm(
            total=len(sampler),
            desc="validation",
            unit="scan",
            leave=False,
            disable=not (self.config.progress and self.ranks.main),
        )
        for batch in self._loader(self.val_set, sampler):
            images = batch["image"].to(self.device)
            labels = batch["label"].to(self.device)
            with forward_precision(self.precision, self.device):
                logits = self.model(images)
            loss, _ = self.criterion(logits, labels)
            loss_sum[0] += loss.double() * len(images)
            loss_sum[1] += len(images)
            argmax = logits.argmax(dim=1)
            counts[0] += torch.bincount((argmax * c + labels).reshape(-1), minlength=c * c)
            for i in range(len(images)):
                truth = batch["point_labels"][i].to(self.device)
                projection = (
                    batch["proj_x"][i],
                    batch["proj_y"][i],
                    batch["proj_range"][i],
                    batch["unproj_range"][i],
                )
                rule = {"votes_from": self.profile.knn.votes_from, "unlabeled": self.unlabeled}
                points = point_classes(argmax[i], *projection, None, c, **rule)
                refined = point_classes(argmax[i], *projection, self.knn, c, **rule)
                counts[1] += torch.bincount(points * c + truth, minlength=c * c)
                counts[2] += torch.bincount(refined.to(truth.dtype) * c + truth, minlength=c * c)
            bar.update(len(images))
        bar.close()
        counts = self.ranks.sum(counts)
        loss_sum = self.ranks.sum(loss_sum).cpu()
        image, points, knn = (self._matrix(counts[i]) for i in range(3))
        return {
            "val_loss": float(loss_sum[0] / max(loss_sum[1], 1)),
            "val_miou_image": image.miou(),
            "val_acc_image": image.accuracy(),
            "val_miou_points": points.miou(),
            "val_acc_points": points.accuracy(),
            "val_miou_knn": knn.miou(),
            "val_acc_knn": knn.accuracy(),
        }

    # Saving and resuming ---------------------------------------------------------------------

    def _improved(self, metrics: Mapping[str, Any]) -> bool:
        """Whether `metrics` beat the best epoch so far (and record them as the best if so)."""
        if "val_miou_knn" in metrics:
            name, value, better = "val_miou_knn", metrics["val_miou_knn"], max
        else:
            name, value, better = "train_loss", metrics["train_loss"], min
        if self.best is not None and better(value, self.best["value"]) == self.best["value"]:
            return False
        self.best = {
            "metric": name,
            "value": value,
            "epoch": metrics["epoch"],
            "step": metrics["step"],
        }
        return True

    def _metadata(
        self, epoch: int, complete: bool, metrics: Mapping[str, Any] | None
    ) -> dict[str, Any]:
        config = self.config
        return {
            "epoch": epoch + 1,
            "epoch_complete": complete,
            "step": self.step,
            "total_steps": self.total_steps,
            "metrics": dict(metrics) if metrics else None,
            "best": dict(self.best) if self.best else None,
            "optimizer": {"name": "AdamW", "lr": config.lr, "weight_decay": config.weight_decay},
            "scheduler": {
                "name": "OneCycleLR" if config.schedule == "onecycle" else "warmup-cosine",
                "max_lr": config.max_lr,
                "warmup": config.warmup,
            },
            "losses": list(self.criterion.losses),
            "class_weighting": config.class_weighting,
            "precision": self.precision,
            "world_size": self.ranks.world_size,
            "train_scans": len(self.train_set),
            "val_scans": len(self.val_set),
            "train_config": config.to_dict(),
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
