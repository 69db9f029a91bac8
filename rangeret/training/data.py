"""Range-image samples from a dataset tree, for training and validation.

A sample is one scan, read with the dataset profile's point record: its points (augmented when
training), projected with the run's `ProjectionConfig` (rows from pitch or laser id); its raw
labels mapped through the label configuration to training classes (unknown ids give the unlabeled
class); and the (H, W) label image, where each pixel takes the class of the point that won it
(the closest). Pixels without a point hold the unlabeled class (0 for SemanticKITTI, 14 for
PandaSet), which the losses ignore.

Randomness is a function of (seed, epoch, scan index) only: the sampler hands the dataset
`(epoch, index)` keys, and every draw for that sample (augmentation, mix partner, mix parameters)
comes from a generator seeded with them. The same run therefore sees the same samples whatever
the number of loader processes, and a resumed run continues exactly where it stopped.

`find_scans` lists a split's labelled scans in the profile's layout, `training_profile` is the
profile a `TrainConfig` trains with, and `run_datasets` gives a run its training and validation
sets.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.layout import DatasetLayoutError, ScanEntry, discover, resolve_sequences
from rangeret.dataset.profiles import DatasetProfile, ProfileError, profile_of_record
from rangeret.dataset.projection import ProjectionConfig, project_with
from rangeret.io.scans import PointRecord, read_scan
from rangeret.training.augment import augment_points
from rangeret.training.config import TrainConfig
from rangeret.training.range_mixes import MixSettings, RangeImage, rare_classes

log = logging.getLogger("rangeret.training")

#: Keys of a sample that are per-point arrays (validation only), kept as lists when batching.
POINT_KEYS = ("proj_x", "proj_y", "unproj_range", "point_labels")


class RangeDataset(Dataset):
    """Scans of a dataset tree as range images with per-pixel training classes.

    `points` is the scan files' point record (the profile's). `augment` applies the thesis's point augmentations, `mixing` RangeFormer's image mixes (both
    for training). With `with_points` a sample also carries what point-level validation needs:
    every point's pixel and range, its class, and the (H, W) range image.
    """

    def __init__(
        self,
        scans: Sequence[ScanEntry],
        projection: ProjectionConfig,
        label_config: LabelConfig,
        *,
        augment: bool = False,
        mixing: MixSettings | None = None,
        seed: int = 0,
        with_points: bool = False,
        points: PointRecord,
    ) -> None:
        missing = [s.key for s in scans if s.label_path is None]
        if missing:
            raise DatasetLayoutError(
                f"{len(missing)} scan(s) have no labels, the first {missing[0]}"
            )
        self.scans = list(scans)
        self.projection = projection
        self.label_config = label_config
        self.record = points
        self.augment = augment
        self.mixing = mixing
        self.seed = seed
        self.with_points = with_points

    def __len__(self) -> int:
        return len(self.scans)

    def rng(self, epoch: int, index: int) -> np.random.Generator:
        """The generator of every random draw for scan `index` in `epoch`."""
        return np.random.default_rng([self.seed, epoch, index])

    def points_and_classes(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(N, fields) float32 points and (N,) int64 training classes of scan `index`."""
        entry = self.scans[index]
        points = read_scan(entry.scan_path, record=self.record)
        raw = entry.label_file.read(entry.label_path, num_points=len(points))
        return points, self.label_config.to_class(raw).astype(np.int64)

    def class_counts(self) -> np.ndarray:
        """(num_classes,) number of points of each training class over all scans (reads every label)."""
        counts = np.zeros(self.label_config.num_classes, dtype=np.int64)
        for entry in self.scans:
            classes = self.label_config.to_class(entry.label_file.read(entry.label_path))
            counts += np.bincount(classes, minlength=counts.size)
        return counts

    def _sample(
        self, index: int, rng: np.random.Generator | None
    ) -> tuple[RangeImage, dict[str, Any]]:
        points, classes = self.points_and_classes(index)
        if rng is not None:
            points = augment_points(points, rng)
        proj = project_with(points, self.projection)
        empty = self.label_config.unlabeled_class
        sample = RangeImage(proj.image, proj.to_image(classes, fill=empty), proj.mask)
        extra: dict[str, Any] = {}
        if self.with_points:
            extra = {
                "proj_x": proj.proj_x,
                "proj_y": proj.proj_y,
                "unproj_range": proj.unproj_range,
                "point_labels": classes,
                "proj_range": proj.proj_range,
            }
        return sample, extra

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        """The sample of `key`, an index or an (epoch, index) pair: arrays by name."""
        epoch, index = (0, key) if isinstance(key, (int, np.integer)) else key
        rng = self.rng(epoch, index)
        sample, extra = self._sample(index, rng if self.augment else None)
        if self.mixing is not None:

            def partner() -> RangeImage:
                other = int(rng.integers(len(self)))
                child = np.random.default_rng(rng.integers(1 << 62))
                return self._sample(other, child if self.augment else None)[0]

            sample = self.mixing.apply(sample, partner, rng)
        return {
            "image": sample.image,
            "label": sample.label,
            "mask": sample.mask,
            **extra,
            "index": index,
        }


def collate(samples: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Stack the images, labels, masks and range images of samples into tensors; per-point
    arrays (different lengths) become lists of tensors, indices a list of ints."""
    out: dict[str, Any] = {}
    for key in samples[0]:
        values = [s[key] for s in samples]
        if key == "index":
            out[key] = [int(v) for v in values]
        elif key in POINT_KEYS:
            out[key] = [torch.from_numpy(np.ascontiguousarray(v)) for v in values]
        else:
            out[key] = torch.from_numpy(np.stack(values))
    return out


class EpochSampler(Sampler):
    """(epoch, index) keys of one epoch for one rank: a seeded permutation of the scans, padded by
    wrapping to a multiple of the world size and dealt out rank by rank, from batch `start` on.

    Every rank gets the same number of samples, so data-parallel ranks take the same number of
    steps; with `shuffle` off the order is the dataset's.
    """

    def __init__(
        self,
        size: int,
        epoch: int,
        seed: int,
        *,
        batch_size: int = 1,
        rank: int = 0,
        world_size: int = 1,
        start: int = 0,
        shuffle: bool = True,
        pad: bool = True,
    ) -> None:
        self.size = size
        self.epoch = epoch
        self.seed = seed
        self.batch_size = batch_size
        self.rank = rank
        self.world_size = world_size
        self.start = start
        self.shuffle = shuffle
        self.pad = pad

    def indices(self) -> list[int]:
        """This rank's scan indices for the whole epoch, before skipping `start` batches."""
        if self.shuffle:
            gen = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            order = torch.randperm(self.size, generator=gen).tolist()
        else:
            order = list(range(self.size))
        if self.pad and self.size:
            total = math.ceil(self.size / self.world_size) * self.world_size
            order = (order * math.ceil(total / self.size))[:total]
        return order[self.rank :: self.world_size]

    def __iter__(self) -> Iterator[tuple[int, int]]:
        for index in self.indices()[self.start * self.batch_size :]:
            yield (self.epoch, index)

    def __len__(self) -> int:
        return max(len(self.indices()) - self.start * self.batch_size, 0)


def steps_per_epoch(size: int, batch_size: int, world_size: int = 1) -> int:
    """Optimiser steps in one epoch over `size` scans on each of `world_size` ranks."""
    return math.ceil(math.ceil(size / world_size) / batch_size)


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
        resolve_sequences(sequences=sequences, labels=profile.labels, layout=layout)
        if sequences is not None
        else [
            layout.normalise(s)
            for s in resolve_sequences(split=split, labels=profile.labels, layout=layout)
        ]
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


@dataclass(frozen=True)
class RunData:
    """A run's training and validation sets, and the class frequencies its losses weigh by."""

    train: RangeDataset
    valid: RangeDataset
    frequencies: np.ndarray


def run_datasets(config: TrainConfig, profile: DatasetProfile) -> RunData:
    """The training set (augmented and mixed as `config` says) and the validation set (with
    what point-level validation needs) of `config`'s scans; no training scan is an error."""
    train_scans = find_scans(config.dataset, config.train_sequences, "train", profile)
    val_split = "valid" if "valid" in profile.splits else "val"
    val_scans = find_scans(config.dataset, config.val_sequences, val_split, profile)
    if not train_scans:
        raise DatasetLayoutError(f"no labelled training scan under {config.dataset}")
    frequencies = class_frequencies(train_scans, profile)
    mixing = None
    if config.mixes:
        paste = rare_classes(frequencies, profile.labels.ignored)
        mixing = MixSettings(tuple(config.mixes), config.mix_probability, paste)
    common = {
        "projection": profile.projection,
        "label_config": profile.labels,
        "seed": config.seed,
        "points": profile.points,
    }
    return RunData(
        RangeDataset(train_scans, augment=config.augment, mixing=mixing, **common),
        RangeDataset(val_scans, with_points=True, **common),
        frequencies,
    )


def class_frequencies(scans: Sequence[ScanEntry], profile: DatasetProfile) -> np.ndarray:
    """Shares of points per class: the label configuration's, or counted over the labels of
    `scans` when the configuration has none (data from another sensor)."""
    labels = profile.labels
    freq = labels.class_frequencies()
    evaluated = [c for c in range(labels.num_classes) if not labels.ignored[c]]
    if freq[evaluated].sum() > 0:
        return freq
    log.info("the label configuration has no class frequencies: counting the training labels")
    counts = RangeDataset(scans, profile.projection, labels, points=profile.points).class_counts()
    return counts / max(counts.sum(), 1)
