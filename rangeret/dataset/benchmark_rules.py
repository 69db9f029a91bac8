"""A profile's `benchmark` section: what its benchmark accepts and how it scores, and which
registry entries (`rangeret.submission.benchmarks`) write and check its archives.

The defaults are SemanticKITTI's; a section without `name` or `panoptic` keeps what profiles
meant before they could name them (`default_benchmark`). Torch-free.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from rangeret.dataset.fields import Fields
from rangeret.evaluation.scoring import SCORINGS, SERVER_SCORING

#: What a benchmark's prediction files hold: raw ids (the label configuration's inverse map, as
#: SemanticKITTI's) or the training classes themselves (nuScenes-lidarseg's challenge indices).
PREDICTION_IDS = ("raw", "class")
#: The benchmark a profile without `benchmark.name` has: SemanticKITTI's for a profile named
#: `semantickitti`, nuScenes-lidarseg's for one of a version's tables, none for the others.
KITTI_BENCHMARK = "semantickitti"
TABLES_BENCHMARK = "nuscenes-lidarseg"
#: The panoptic benchmark each of those has where `benchmark.panoptic` is left out.
PANOPTIC_BENCHMARKS = {
    KITTI_BENCHMARK: "semantickitti-panoptic",
    TABLES_BENCHMARK: "nuscenes-panoptic",
}


@dataclass(frozen=True)
class BenchmarkRules:
    """What a dataset's benchmark accepts and how it scores: the profile's optional `benchmark`
    section. The defaults are SemanticKITTI's (and the release's for every dataset); `name` is
    the benchmark's entry in the registry (`rangeret.submission.benchmarks`), None for a dataset
    without one."""

    #: The registry entry that writes and checks the benchmark's archive; None: no benchmark.
    name: str | None = None
    #: The registry entry of the dataset's panoptic benchmark (`--panoptic`); None: none.
    panoptic: str | None = None
    #: What prediction files hold (`PREDICTION_IDS`).
    predictions: str = "raw"
    #: The network chooses among classes classes_from..C-1 (nuScenes refuses class 0, ignore).
    classes_from: int = 0
    #: The class of a point that projects nowhere; None: the label configuration's unlabeled one.
    unprojected_class: int | None = None
    #: How IoU is computed (a name of `rangeret.evaluation.scoring.SCORINGS`).
    scoring: str = SERVER_SCORING.name

    def to_dict(self) -> dict[str, Any]:
        """The `benchmark` section."""
        return {
            "name": self.name,
            "panoptic": self.panoptic,
            "predictions": self.predictions,
            "classes_from": self.classes_from,
            "unprojected_class": self.unprojected_class,
            "scoring": self.scoring,
        }


_BENCHMARK_KEYS = ("predictions", "classes_from", "unprojected_class", "scoring")
_BENCHMARK_OPTIONAL = ("name", "panoptic")


def default_benchmark(name: str, layout_data: Mapping[str, Any]) -> str | None:
    """The registry entry of a profile whose `benchmark` section names none, as profiles meant
    before they could name one."""
    if "tables" in layout_data:
        return TABLES_BENCHMARK
    return KITTI_BENCHMARK if name == KITTI_BENCHMARK else None


def read_benchmark(f: Fields, num_classes: int, default_name: str | None) -> BenchmarkRules:
    """The optional `benchmark` section (SemanticKITTI's rules where it is left out)."""
    default_panoptic = PANOPTIC_BENCHMARKS.get(default_name or "")
    if "benchmark" not in f.data:
        return BenchmarkRules(name=default_name, panoptic=default_panoptic)
    section = f.section("benchmark", _BENCHMARK_KEYS, _BENCHMARK_OPTIONAL)
    name = _entry_name(section, "name", default_name)
    panoptic = _entry_name(section, "panoptic", PANOPTIC_BENCHMARKS.get(name or ""))
    unprojected = section.data["unprojected_class"]
    if unprojected is not None:
        unprojected = section.integer("unprojected_class", 0, num_classes - 1)
    return BenchmarkRules(
        name=name,
        panoptic=panoptic,
        predictions=section.choice("predictions", PREDICTION_IDS),
        classes_from=section.integer("classes_from", 0, num_classes - 1),
        unprojected_class=unprojected,
        scoring=section.choice("scoring", tuple(SCORINGS)),
    )


def _entry_name(section: Fields, key: str, default: str | None) -> str | None:
    """An optional registry entry's name of the `benchmark` section (null: none)."""
    if key not in section.data:
        return default
    if section.data[key] is None:
        return None
    name = section.get(key, str)
    if not name.strip():
        section.fail(key, "must name a benchmark, or be null for none")
    return name
