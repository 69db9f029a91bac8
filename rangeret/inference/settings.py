"""The settings of a run's post-processing, torch-free so option parsing and settings stay light:
kNN refinement (its parameters; each profile keeps its own voting rule), test-time augmentation
and the clustering of objects for panoptic segmentation."""

from __future__ import annotations

import math
from dataclasses import dataclass

from rangeret.dataset.fields import is_int, is_number
from rangeret.exceptions import InputError


class KnnSettingsError(InputError, ValueError):
    """kNN refinement parameters that cannot be used."""


@dataclass(frozen=True)
class KnnSettings:
    """kNN refinement parameters (a run without refinement has None instead); the defaults are
    those the released checkpoints were scored with. Checked when made, so refinement need not."""

    k: int = 7
    search: int = 7
    sigma: float = 1.0
    cutoff: float = 1.0

    def __post_init__(self) -> None:
        problem = _knn_problem(self.k, self.search, self.sigma, self.cutoff)
        if problem is not None:
            raise KnnSettingsError(problem)


def _knn_problem(k: object, search: object, sigma: object, cutoff: object) -> str | None:
    """What is wrong with kNN parameters, naming the parameter; None when they can be used."""
    if not is_int(search) or search < 1 or search % 2 == 0:
        return f"search must be an odd integer >= 1, got {search!r}"
    if not is_int(k) or k < 1:
        return f"k must be an integer >= 1, got {k!r}"
    if k > search * search:
        return f"k must be at most search**2 = {search * search}, got {k}"
    if not is_number(sigma) or not sigma > 0:
        return f"sigma must be a number > 0, got {sigma!r}"
    if not is_number(cutoff) or math.isnan(cutoff):
        return f"cutoff must be a number (<= 0 for no cutoff), got {cutoff!r}"
    return None


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


class ClusterSettingsError(InputError, ValueError):
    """Clustering parameters that cannot be used."""


#: The angle criterion's threshold in degrees: Bogoslavskyi and Stachniss's choice for 64-beam
#: scans, which separates objects one behind the other and keeps a slanted surface whole.
DEFAULT_CLUSTER_ANGLE = 10.0
#: Clusters with fewer points join the nearest object of their class (`rangeret.inference.instances`).
DEFAULT_MIN_CLUSTER_POINTS = 10


@dataclass(frozen=True)
class ClusterSettings:
    """How the points of each thing class become objects: neighbouring pixels join where the
    angle criterion exceeds `angle` (degrees), and clusters under `min_points` points merge into
    the nearest object of their class."""

    angle: float = DEFAULT_CLUSTER_ANGLE
    min_points: int = DEFAULT_MIN_CLUSTER_POINTS

    def __post_init__(self) -> None:
        if not is_number(self.angle) or not 0 < self.angle < 90:
            raise ClusterSettingsError(
                f"angle must be a number of degrees in (0, 90), got {self.angle!r}"
            )
        if not is_int(self.min_points) or self.min_points < 1:
            raise ClusterSettingsError(
                f"min_points must be an integer >= 1, got {self.min_points!r}"
            )
