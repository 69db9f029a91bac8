"""The settings of a run's post-processing, torch-free so option parsing and settings stay light:
kNN refinement (its parameters; each profile keeps its own voting rule) and test-time augmentation."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class KnnSettings:
    """kNN refinement parameters; the defaults are those the released checkpoints were scored with."""

    k: int = 7
    search: int = 7
    sigma: float = 1.0
    cutoff: float = 1.0


#: The refinement every runner applies unless told otherwise.
DEFAULT_KNN = KnnSettings()


@dataclass(frozen=True)
class TtaSettings:
    """Test-time augmentation: mirror the range image and/or rotate it in azimuth, average logits."""

    flip: bool = True
    shifts: int = 0

    def views(self, width: int) -> list[tuple[bool, int]]:
        """(flipped, column shift) of every view, the identity first."""
        shifts = [round(i * width / (self.shifts + 1)) for i in range(self.shifts + 1)]
        return [(f, s) for f in ([False, True] if self.flip else [False]) for s in shifts]
