"""RangeFormer's range-image augmentations (thesis section 2.6): RangeMix, RangeUnion, RangePaste
and RangeShift.

They act on projected samples, after the point augmentations: a `RangeImage` holds the normalised
(5, H, W) input, the (H, W) training classes and the (H, W) mask of filled pixels. Every mix moves
whole pixels (all five channels, the class and the mask together), so a pixel's label always
describes the point it holds.

- RangeMix: the image is cut into k equal strips along the inclination (rows), the azimuth
  (columns) or both (a k x k checkerboard), k drawn from 2..6, and every other strip comes from
  the second scan.
- RangeUnion: of the pixels empty in the first scan and filled in the second, a random half is
  filled from the second.
- RangePaste: the second scan's pixels of rare classes are copied at the same positions.
- RangeShift: the image rolls along the azimuth by k columns, k drawn from [W/4, 3W/4], as if the
  sensor's heading had turned (all channels move, as in RangeFormer).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: The mixes by name, in the order they are applied.
MIXES = ("rangemix", "rangeunion", "rangepaste", "rangeshift")
#: Numbers of strips RangeMix draws from.
MIX_STRIPS = (2, 3, 4, 5, 6)
#: Share of the candidate empty pixels RangeUnion fills (RangeFormer's k_union).
UNION_SHARE = 0.5
#: Classes rarer than this share of points are pasted by RangePaste.
RARE_SHARE = 0.01


@dataclass
class RangeImage:
    """A projected training sample: (5, H, W) float32 input, (H, W) int64 classes, (H, W) bool mask."""

    image: np.ndarray
    label: np.ndarray
    mask: np.ndarray

    def copy(self) -> RangeImage:
        """A deep copy."""
        return RangeImage(self.image.copy(), self.label.copy(), self.mask.copy())

    def take(self, other: RangeImage, where: np.ndarray) -> RangeImage:
        """A copy of this sample with the pixels `where` (H, W) taken from `other`."""
        out = self.copy()
        out.image[:, where] = other.image[:, where]
        out.label[where] = other.label[where]
        out.mask[where] = other.mask[where]
        return out


def range_mix(a: RangeImage, b: RangeImage, rng: np.random.Generator) -> RangeImage:
    """`a` with every other strip (rows, columns or a checkerboard of both) taken from `b`."""
    h, w = a.label.shape
    strips = int(rng.choice(MIX_STRIPS))
    direction = int(rng.integers(3))
    row_strip = np.minimum(np.arange(h) * strips // h, strips - 1)
    col_strip = np.minimum(np.arange(w) * strips // w, strips - 1)
    if direction == 0:
        where = np.broadcast_to((row_strip % 2 == 1)[:, None], (h, w))
    elif direction == 1:
        where = np.broadcast_to((col_strip % 2 == 1)[None, :], (h, w))
    else:
        where = (row_strip[:, None] + col_strip[None, :]) % 2 == 1
    return a.take(b, where)


def range_union(
    a: RangeImage, b: RangeImage, rng: np.random.Generator, share: float = UNION_SHARE
) -> RangeImage:
    """`a` with a random `share` of its empty pixels that `b` fills taken from `b`."""
    candidates = ~a.mask & b.mask
    where = candidates & (rng.random(candidates.shape) < share)
    return a.take(b, where)


def range_paste(a: RangeImage, b: RangeImage, classes: Sequence[int]) -> RangeImage:
    """`a` with `b`'s pixels of `classes` copied at the same positions."""
    where = np.isin(b.label, np.asarray(classes, dtype=np.int64)) & b.mask
    return a.take(b, where)


def range_shift(a: RangeImage, rng: np.random.Generator) -> RangeImage:
    """`a` rolled along the azimuth by a number of columns drawn from [W/4, 3W/4]."""
    w = a.label.shape[1]
    shift = int(rng.integers(w // 4, max(3 * w // 4, w // 4 + 1)))
    return RangeImage(
        np.roll(a.image, shift, axis=-1),
        np.roll(a.label, shift, axis=-1),
        np.roll(a.mask, shift, axis=-1),
    )


def rare_classes(
    frequencies: np.ndarray, ignored: Sequence[bool], share: float = RARE_SHARE
) -> tuple[int, ...]:
    """Evaluated classes whose share of points is below `share` (what RangePaste copies)."""
    return tuple(
        int(c) for c in range(len(frequencies)) if not ignored[c] and frequencies[c] < share
    )


@dataclass(frozen=True)
class MixSettings:
    """Which mixes to apply, each independently with `probability`, and RangePaste's classes."""

    mixes: tuple[str, ...]
    probability: float = 0.5
    paste_classes: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        unknown = sorted(set(self.mixes) - set(MIXES))
        if unknown:
            raise ValueError(f"unknown mixes {', '.join(unknown)}; known: {', '.join(MIXES)}")
        if not 0.0 <= self.probability <= 1.0:
            raise ValueError(f"the mix probability must lie in [0, 1], got {self.probability}")

    def apply(
        self, sample: RangeImage, partner: Callable[[], RangeImage], rng: np.random.Generator
    ) -> RangeImage:
        """`sample` after the chosen mixes; `partner()` loads the second scan, at most once."""
        second: RangeImage | None = None
        for name in MIXES:
            if name not in self.mixes or rng.random() >= self.probability:
                continue
            if name == "rangeshift":
                sample = range_shift(sample, rng)
                continue
            if second is None:
                second = partner()
            if name == "rangemix":
                sample = range_mix(sample, second, rng)
            elif name == "rangeunion":
                sample = range_union(sample, second, rng)
            else:
                sample = range_paste(sample, second, self.paste_classes)
        return sample
