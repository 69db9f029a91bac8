"""The label configuration: raw SemanticKITTI ids, training classes, colours and splits.

The default configuration is the project's own `data/semantickitti.json`. A configuration in the
official `semantic-kitti.yaml` layout (keys `labels`, `learning_map`, `learning_map_inv`,
`learning_ignore`, `color_map`, `split`) can be loaded too, for data from other sensors.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from rangeret import DATA_DIR
from rangeret.exceptions import ConfigError

#: Raw labels are the low 16 bits of each uint32 in a `.label` file.
SEMANTIC_MASK = 0xFFFF


class LabelConfigError(ConfigError, ValueError):
    """A label configuration that cannot be used: unreadable, inconsistent, or without a split."""


@dataclass(frozen=True)
class LabelConfig:
    """Maps between raw label ids and training classes, with names, colours and splits."""

    class_names: tuple[str, ...]
    class_raw_ids: tuple[int, ...]
    ignored: tuple[bool, ...]
    raw_names: dict[int, str]
    raw_to_class: dict[int, int]
    raw_bgr: dict[int, tuple[int, int, int]]
    raw_frequency: dict[int, float]
    splits: dict[str, tuple[str, ...]]
    unlabeled_class: int | None = None
    _lut: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.class_names) != len(self.class_raw_ids) or len(self.ignored) != len(
            self.class_names
        ):
            raise LabelConfigError(
                "label configuration: classes, raw ids and ignore flags differ in length"
            )
        if self.unlabeled_class is None:
            default = self.raw_to_class.get(0, self.ignored.index(True) if any(self.ignored) else 0)
            object.__setattr__(self, "unlabeled_class", default)
        if not 0 <= self.unlabeled_class < self.num_classes:
            raise LabelConfigError(
                f"label configuration: the unlabeled class {self.unlabeled_class} is not a class"
            )
        lut = np.full(SEMANTIC_MASK + 1, self.unlabeled_class, dtype=np.uint8)
        for raw, cls in self.raw_to_class.items():
            if not 0 <= raw <= SEMANTIC_MASK:
                raise LabelConfigError(f"label configuration: raw id {raw} does not fit in 16 bits")
            if not 0 <= cls < self.num_classes:
                raise LabelConfigError(
                    f"label configuration: raw id {raw} maps to unknown class {cls}"
                )
            lut[raw] = cls
        object.__setattr__(self, "_lut", lut)

    @property
    def num_classes(self) -> int:
        """Number of training classes, the ignored ones included (20 for SemanticKITTI)."""
        return len(self.class_names)

    @property
    def evaluated_classes(self) -> list[int]:
        """Training classes that count in mIoU (all but the ignored ones)."""
        return [c for c in range(self.num_classes) if not self.ignored[c]]

    @property
    def raw_lut(self) -> np.ndarray:
        """(65536,) uint8 table from a 16-bit raw id to its training class; unknown ids give the
        unlabeled class (0 for SemanticKITTI, the class raw id 0 maps to in general)."""
        return self._lut

    @property
    def inverse_lut(self) -> np.ndarray:
        """(num_classes,) uint32 table from a training class back to its raw id."""
        return np.asarray(self.class_raw_ids, dtype=np.uint32)

    @property
    def valid_prediction_ids(self) -> frozenset[int]:
        """Raw ids a prediction may hold: those the inverse map can produce."""
        return frozenset(self.class_raw_ids)

    def to_class(self, raw: np.ndarray) -> np.ndarray:
        """Training classes (uint8) of raw labels; instance bits are dropped, unknown ids give the
        unlabeled class."""
        raw = np.asarray(raw)
        return self._lut[raw.astype(np.int64, copy=False) & SEMANTIC_MASK]

    def to_raw(self, classes: np.ndarray) -> np.ndarray:
        """Raw ids (uint32) of training classes."""
        return self.inverse_lut[np.asarray(classes)]

    def class_bgr(self) -> np.ndarray:
        """(num_classes, 3) uint8 BGR colour of each training class."""
        return np.array([self.raw_bgr[r] for r in self.class_raw_ids], dtype=np.uint8)

    def class_rgb(self) -> np.ndarray:
        """(num_classes, 3) uint8 RGB colour of each training class, for plots."""
        return self.class_bgr()[:, ::-1].copy()

    def class_frequencies(self) -> np.ndarray:
        """(num_classes,) share of points in each training class, summed over its raw ids."""
        freq = np.zeros(self.num_classes, dtype=np.float64)
        for raw, share in self.raw_frequency.items():
            freq[self.raw_to_class.get(raw, self.unlabeled_class)] += share
        return freq

    def split(self, name: str) -> tuple[str, ...]:
        """Sequence names (two digits) of a split such as "train", "valid" or "test"."""
        try:
            return self.splits[name]
        except KeyError:
            raise LabelConfigError(
                f"unknown split {name!r}; the label configuration has {sorted(self.splits)}"
            ) from None

    def to_dict(self) -> dict:
        """Plain-data form (JSON-safe), as stored in checkpoints and reports."""
        return {
            "class_names": list(self.class_names),
            "class_raw_ids": list(self.class_raw_ids),
            "ignored": list(self.ignored),
            "raw_names": {str(k): v for k, v in self.raw_names.items()},
            "raw_to_class": {str(k): v for k, v in self.raw_to_class.items()},
            "raw_bgr": {str(k): list(v) for k, v in self.raw_bgr.items()},
            "raw_frequency": {str(k): v for k, v in self.raw_frequency.items()},
            "splits": {k: list(v) for k, v in self.splits.items()},
            "unlabeled_class": self.unlabeled_class,
        }

    @classmethod
    def from_dict(cls, data: dict) -> LabelConfig:
        """Rebuild a configuration from `to_dict()`'s form."""
        return cls(
            class_names=tuple(data["class_names"]),
            class_raw_ids=tuple(int(v) for v in data["class_raw_ids"]),
            ignored=tuple(bool(v) for v in data["ignored"]),
            raw_names={int(k): v for k, v in data.get("raw_names", {}).items()},
            raw_to_class={int(k): int(v) for k, v in data["raw_to_class"].items()},
            raw_bgr={int(k): tuple(v) for k, v in data.get("raw_bgr", {}).items()},
            raw_frequency={int(k): float(v) for k, v in data.get("raw_frequency", {}).items()},
            splits={k: tuple(v) for k, v in data.get("splits", {}).items()},
            unlabeled_class=data.get("unlabeled_class"),
        )

    @classmethod
    def from_json(cls, path: Path | str) -> LabelConfig:
        """Load the project's own JSON layout."""
        data = json.loads(Path(path).read_text())
        classes = sorted(data["classes"], key=lambda c: c["id"])
        if [c["id"] for c in classes] != list(range(len(classes))):
            raise LabelConfigError(f"{path}: training class ids must be 0..N-1 without gaps")
        raw = data["raw_labels"]
        return cls(
            class_names=tuple(c["name"] for c in classes),
            class_raw_ids=tuple(int(c["raw_id"]) for c in classes),
            ignored=tuple(bool(c["ignored"]) for c in classes),
            raw_names={int(r["id"]): r["name"] for r in raw},
            raw_to_class={int(r["id"]): int(r["class"]) for r in raw},
            raw_bgr={int(r["id"]): tuple(r["bgr"]) for r in raw},
            raw_frequency={int(r["id"]): float(r.get("frequency", 0.0)) for r in raw},
            splits={k: tuple(v) for k, v in data["splits"].items()},
        )

    @classmethod
    def from_official_yaml(cls, path: Path | str) -> LabelConfig:
        """Load a configuration in the official `semantic-kitti.yaml` layout (read within the
        bounds of `rangeret.io.bounded_yaml`)."""
        from rangeret.io.bounded_yaml import load_yaml

        data = load_yaml(path)
        inv = {int(k): int(v) for k, v in data["learning_map_inv"].items()}
        n = len(inv)
        if sorted(inv) != list(range(n)):
            raise LabelConfigError(f"{path}: learning_map_inv must cover classes 0..N-1")
        names = data["labels"]
        ignore = data.get("learning_ignore", {0: True})
        return cls(
            class_names=tuple(names.get(inv[c], f"class-{c}") for c in range(n)),
            class_raw_ids=tuple(inv[c] for c in range(n)),
            ignored=tuple(bool(ignore.get(c, False)) for c in range(n)),
            raw_names={int(k): v for k, v in names.items()},
            raw_to_class={int(k): int(v) for k, v in data["learning_map"].items()},
            raw_bgr={int(k): tuple(v) for k, v in data.get("color_map", {}).items()},
            raw_frequency={int(k): float(v) for k, v in data.get("content", {}).items()},
            splits={k: tuple(f"{int(s):02d}" for s in v) for k, v in data.get("split", {}).items()},
        )


def load_label_config(path: Path | str | None = None) -> LabelConfig:
    """The label configuration at `path` (.json or official .yaml), or the bundled SemanticKITTI one."""
    if path is None:
        return semantickitti()
    path = Path(path)
    if path.suffix in {".yaml", ".yml"}:
        return LabelConfig.from_official_yaml(path)
    return LabelConfig.from_json(path)


@cache
def semantickitti() -> LabelConfig:
    """The bundled SemanticKITTI configuration (20 training classes, class 0 ignored)."""
    return LabelConfig.from_json(DATA_DIR / "semantickitti.json")
