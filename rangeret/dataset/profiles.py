"""Dataset profiles: everything that differs between datasets and sensors, held as data.

A profile gathers the sensor's projection (resolution, field of view, input normalisation, where a
point's row comes from), the point record of its scan files, its label configuration, the kNN
voting rule, its layout (folders of sequences, or a version's tables), its splits and what its
benchmark accepts. Four are built in: the release's three (`semantickitti`, the default,
`semantic-poss` and `pandaset`) and `nuscenes`, in `data/profiles/`; a YAML file with exactly the
fields that `rangeret profile show NAME` prints describes any other sensor.
Torch-free.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from rangeret import DATA_DIR
from rangeret.dataset.benchmark_rules import BenchmarkRules, default_benchmark, read_benchmark
from rangeret.dataset.fields import Fields
from rangeret.dataset.labels import LabelConfig, LabelConfigError, parse_label_config
from rangeret.dataset.layout import DatasetLayout, SequenceLayout
from rangeret.dataset.projection import BEAM_ROWS, ROW_SOURCES, ProjectionConfig
from rangeret.dataset.table_layout import SCHEMAS, TableLayout
from rangeret.exceptions import ConfigError
from rangeret.io.scans import PointRecord

PROFILES_DIR = DATA_DIR / "profiles"
#: The profile the command line and the gateway's settings apply when none is named.
DEFAULT_PROFILE = "semantickitti"
#: Files written before profiles existed (checkpoints, run records) were all SemanticKITTI's.
LEGACY_PROFILE = "semantickitti"
BUILTIN_PROFILES = ("semantickitti", "semantic-poss", "pandaset", "nuscenes")


class ProfileError(ConfigError, ValueError):
    """A profile that cannot be used: unknown name, unreadable file, or a field that is wrong."""


@dataclass(frozen=True)
class KnnVote:
    """Which classes may win the kNN vote: `votes_from`..C-1; a point without a vote gets
    `votes_from`. SemanticKITTI's class 0 (unlabeled) never wins; PandaSet's class 0 is car."""

    votes_from: int = 1


@dataclass(frozen=True)
class DatasetProfile:
    """One dataset's sensor, point record, labels, kNN rule, layout and splits."""

    name: str
    description: str
    projection: ProjectionConfig
    points: PointRecord
    labels: LabelConfig
    knn: KnnVote
    layout: DatasetLayout
    benchmark: BenchmarkRules = field(default_factory=BenchmarkRules)
    #: The reflectance a perfect reflector returns: 1 for remission, 255 for 8-bit intensity.
    reflectance_max: float = 1.0
    #: Elevation of each beam in degrees, top beam first, for sensors whose beams are not evenly
    #: spaced; None: beam i is aimed at the centre of row i.
    beam_angles: tuple[float, ...] | None = None
    #: The farthest return of the sensor in metres; None: not declared.
    max_range: float | None = None
    #: The sensor's height above the ground in metres, as the simulator mounts it; None: its
    #: default.
    mount_height: float | None = None
    #: The classes whose points form objects (panoptic segmentation's "things"), as training
    #: class indices; empty: the profile has none and `--panoptic` is refused.
    things: tuple[int, ...] = ()

    @property
    def thing_names(self) -> list[str]:
        """The names of the thing classes, in class order."""
        return [self.labels.class_names[c] for c in self.things]

    def panoptic_refusal(self) -> str | None:
        """Why the profile cannot give instances (it names no thing class), or None."""
        if self.things:
            return None
        return (
            f"the {self.name} profile names no thing classes, so --panoptic has no objects to "
            "find (add a `things:` list of class names to a profile of your own)"
        )

    @property
    def num_classes(self) -> int:
        """Training classes of the label configuration, the ignored ones included."""
        return self.labels.num_classes

    @property
    def reflectance_fill(self) -> float:
        """The reflectance a point gets when its cloud has none (a PCD or PointCloud2 of x, y, z
        only): the profile's mean reflectance, which the network's input normalises to 0."""
        return float(self.projection.means[4])

    @property
    def splits(self) -> dict[str, tuple[str, ...]]:
        """Sequence ids of each split, as written on disk."""
        return self.labels.splits

    @property
    def unprojected_class(self) -> int:
        """The class a point without a pixel gets."""
        chosen = self.benchmark.unprojected_class
        return self.labels.unlabeled_class if chosen is None else chosen

    def prediction_classes(self, values: np.ndarray) -> np.ndarray:
        """The training classes (uint8) of what a prediction file holds: `output_labels` undone
        (a value no class gives reads as the unlabeled class)."""
        if self.benchmark.predictions == "class":
            values = np.asarray(values)
            known = values < self.num_classes
            return np.where(known, values, self.labels.unlabeled_class).astype(np.uint8)
        return self.labels.to_class(values)

    def output_labels(self, classes: np.ndarray) -> np.ndarray:
        """What a prediction file holds for training classes, uint32: raw ids (the inverse map)
        or the classes themselves, as the benchmark wants."""
        if self.benchmark.predictions == "class":
            return np.asarray(classes).astype(np.uint32)
        return self.labels.to_raw(classes)

    def with_overrides(
        self,
        height: int | None = None,
        width: int | None = None,
        fov_up: float | None = None,
        fov_down: float | None = None,
        labels: LabelConfig | None = None,
    ) -> DatasetProfile:
        """The profile with explicit command-line values in place of its own (None keeps them);
        `beam_angles` describe the profile's own rows, so another height or field of view drops
        them."""
        changes = {
            k: v
            for k, v in (
                ("height", height),
                ("width", width),
                ("fov_up", fov_up),
                ("fov_down", fov_down),
            )
            if v is not None
        }
        projection = replace(self.projection, **changes) if changes else self.projection
        if labels is not None and not labels.splits:
            labels = replace(labels, splits=self.labels.splits)
        beam_angles = self.beam_angles
        if beam_angles is not None and any(
            getattr(projection, k) != getattr(self.projection, k)
            for k in ("height", "fov_up", "fov_down")
        ):
            beam_angles = None
        return replace(
            self, projection=projection, labels=labels or self.labels, beam_angles=beam_angles
        )

    def to_dict(self) -> dict[str, Any]:
        """The profile's fields as plain data: what `profile show` prints and a file holds."""
        p = self.projection
        labels = self.labels
        return {
            "name": self.name,
            "description": self.description,
            "sensor": {
                "height": p.height,
                "width": p.width,
                "fov_up": p.fov_up,
                "fov_down": p.fov_down,
                "row": p.row,
                "means": list(p.means),
                "stds": list(p.stds),
                **({"reflectance_max": self.reflectance_max} if self.reflectance_max != 1 else {}),
                **({"beam_angles": list(self.beam_angles)} if self.beam_angles else {}),
                **({"max_range": self.max_range} if self.max_range is not None else {}),
                **({"mount_height": self.mount_height} if self.mount_height is not None else {}),
            },
            "points": {"fields": list(self.points.fields)},
            "layout": self.layout.to_dict(),
            "knn": {"votes_from": self.knn.votes_from},
            "labels": {
                "unlabeled_class": labels.unlabeled_class,
                "classes": [
                    {"name": n, "raw_id": r, "ignored": i}
                    for n, r, i in zip(
                        labels.class_names, labels.class_raw_ids, labels.ignored, strict=True
                    )
                ],
                "raw_labels": [
                    {
                        "id": raw,
                        "name": labels.raw_names.get(raw, str(raw)),
                        "class": cls,
                        "bgr": list(labels.raw_bgr.get(raw, (0, 0, 0))),
                        "frequency": labels.raw_frequency.get(raw, 0.0),
                    }
                    for raw, cls in sorted(labels.raw_to_class.items())
                ],
            },
            "splits": {k: list(v) for k, v in labels.splits.items()},
            **({"things": self.thing_names} if self.things else {}),
            "benchmark": self.benchmark.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Any, source: str = "profile") -> DatasetProfile:
        """A profile from `to_dict()`'s form; a wrong, missing or extra field is a ProfileError
        naming it (as `source: field.path: problem`)."""
        f = Fields(data, source, error=ProfileError, kind="profile field")
        sensor = f.section("sensor", _SENSOR_KEYS, _SENSOR_OPTIONAL)
        points = f.section("points", ("fields",))
        layout_data = f.get("layout", dict)
        if "tables" in layout_data:
            layout = f.section("layout", ("tables", "channel"))
        else:
            layout = f.section("layout", ("sequence_folders", "id_digits"))
        knn = f.section("knn", ("votes_from",))
        labels = f.section("labels", ("unlabeled_class", "classes", "raw_labels"))
        splits = f.get("splits", dict)
        f.finish(_TOP_KEYS, ("things", "benchmark"))

        height = sensor.integer("height", 1)
        width = sensor.integer("width", 1)
        fov_up, fov_down = sensor.number("fov_up"), sensor.number("fov_down")
        row = sensor.choice("row", ROW_SOURCES)
        means, stds = sensor.numbers("means", 5), sensor.numbers("stds", 5)
        if any(not s > 0 for s in stds):
            sensor.fail("stds", f"must all be positive, got {list(stds)}")
        if fov_up < 0:
            sensor.fail(
                "fov_up", f"must be 0 or more (degrees above the horizontal), got {fov_up:g}"
            )
        if fov_down > 0:
            sensor.fail(
                "fov_down", f"must be 0 or less (degrees below the horizontal), got {fov_down:g}"
            )
        if fov_up - fov_down <= 0:
            sensor.fail("fov_up", "and fov_down leave an empty field of view")
        projection = ProjectionConfig(height, width, fov_up, fov_down, means, stds, row)

        fields = points.strings("fields")
        try:
            record = PointRecord(tuple(fields))
        except ValueError as exc:
            points.fail("fields", str(exc))
        if row in BEAM_ROWS and row not in record.fields[4:]:
            points.fail("fields", f"must end with {row} when sensor.row is {row}")

        reflectance_max = _positive(sensor, "reflectance_max")
        beam_angles = _beam_angles(sensor, projection)

        if "tables" in layout_data:
            tables = layout.choice("tables", SCHEMAS)
            channel = layout.get("channel", str)
            if not channel:
                layout.fail("channel", "must name a sensor channel")
            normalise = str
        else:
            folders = tuple(layout.strings("sequence_folders"))
            if not folders:
                layout.fail("sequence_folders", "must name at least one folder")
            sequence_layout = SequenceLayout(folders, layout.integer("id_digits", 1, 8))
            normalise = sequence_layout.normalise

        try:
            label_config = parse_label_config(
                labels.data,
                source,
                field="labels",
                splits=splits,
                normalise=normalise,
            )
        except LabelConfigError as exc:
            raise ProfileError(str(exc)) from exc
        if "tables" in layout_data:
            sequence_layout = TableLayout(
                tables, channel, label_config.splits, dict(label_config.raw_names)
            )
        votes_from = knn.integer("votes_from", 0, label_config.num_classes - 1)
        name = f.get("name", str)
        if not name.strip():
            f.fail("name", "must not be empty")
        benchmark = read_benchmark(
            f, label_config.num_classes, default_benchmark(name, layout_data)
        )
        things = _things(f, label_config)
        return cls(
            name=name,
            description=f.get("description", str),
            projection=projection,
            points=record,
            labels=label_config,
            knn=KnnVote(votes_from),
            layout=sequence_layout,
            benchmark=benchmark,
            reflectance_max=1.0 if reflectance_max is None else reflectance_max,
            beam_angles=beam_angles,
            max_range=_positive(sensor, "max_range"),
            mount_height=_positive(sensor, "mount_height"),
            things=things,
        )

    def to_yaml(self) -> str:
        """The profile as YAML text that `load_profile` reads back unchanged."""
        import yaml

        class Dumper(yaml.SafeDumper):
            """Quotes every string of digits alike: YAML leaves `08` and `09`, which no integer
            reads as, bare among quoted ids such as `'07'`."""

        def digits(dumper: yaml.SafeDumper, value: str) -> yaml.ScalarNode:
            style = "'" if value.isdigit() else None
            return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)

        Dumper.add_representer(str, digits)
        return yaml.dump(
            self.to_dict(), Dumper=Dumper, sort_keys=False, allow_unicode=True, width=100
        )


_TOP_KEYS = ("name", "description", "sensor", "points", "layout", "knn", "labels", "splits")


def _things(f: Fields, labels: LabelConfig) -> tuple[int, ...]:
    """The optional `things` list: class names of the label configuration, none ignored, each
    once; their class indices in class order."""
    if "things" not in f.data:
        return ()
    names = f.strings("things")
    index = {name: i for i, name in enumerate(labels.class_names)}
    for name in names:
        if name not in index:
            f.fail("things", f"{name!r} is not a class of the profile's labels")
        if labels.ignored[index[name]]:
            f.fail("things", f"{name!r} is an ignored class, which has no objects to score")
    if len(set(names)) != len(names):
        f.fail("things", "names a class twice")
    return tuple(sorted(index[name] for name in names))


_SENSOR_KEYS = ("height", "width", "fov_up", "fov_down", "row", "means", "stds")
_SENSOR_OPTIONAL = ("reflectance_max", "beam_angles", "max_range", "mount_height")


def _positive(sensor: Fields, key: str) -> float | None:
    """An optional positive number of the `sensor` section; None where it is left out."""
    if key not in sensor.data:
        return None
    value = sensor.number(key)
    if not value > 0:
        sensor.fail(key, f"must be positive, got {value:g}")
    return value


def _beam_angles(sensor: Fields, projection: ProjectionConfig) -> tuple[float, ...] | None:
    """The optional `sensor.beam_angles`: one elevation per row in degrees, top beam first,
    strictly decreasing and within the field of view; None where it is left out."""
    if "beam_angles" not in sensor.data:
        return None
    angles = sensor.numbers("beam_angles", projection.height)
    steps = [i for i in range(1, len(angles)) if not angles[i] < angles[i - 1]]
    if steps:
        i = steps[0]
        sensor.fail(
            "beam_angles",
            f"must decrease strictly from the top beam down, but beam {i} ({angles[i]:g}) is not "
            f"below beam {i - 1} ({angles[i - 1]:g})",
        )
    top, bottom = abs(projection.fov_up), -abs(projection.fov_down)
    if angles[0] > top or angles[-1] < bottom:
        sensor.fail(
            "beam_angles",
            f"must lie within the field of view ({bottom:g} to {top:g} degrees), got "
            f"{angles[-1]:g} to {angles[0]:g}",
        )
    return angles


def builtin_profiles() -> list[str]:
    """Names of the built-in profiles, the default first."""
    return list(BUILTIN_PROFILES)


def load_profile(name_or_path: str | Path | None = None) -> DatasetProfile:
    """A built-in profile by name, or a profile YAML file; None gives the default
    (`semantickitti`), which only the command line and the gateway's settings ask for. Anything
    wrong is a ProfileError naming the file and the field."""
    if name_or_path is None:
        return _builtin(DEFAULT_PROFILE)
    text = str(name_or_path)
    if text in BUILTIN_PROFILES:
        return _builtin(text)
    path = Path(text)
    if not path.exists():  # anything else there is read, and refused by its kind if not a file
        raise ProfileError(
            f"unknown profile {text!r}: not a built-in profile ({', '.join(BUILTIN_PROFILES)}) "
            "and no such file"
        )
    return _read(path)


@cache
def _builtin(name: str) -> DatasetProfile:
    return _read(PROFILES_DIR / f"{name}.yaml")


#: The most characters of an error about a profile file (values it quotes are cut short).
MAX_ERROR_CHARS = 400


def _read(path: Path) -> DatasetProfile:
    from rangeret.io.bounded_yaml import read_yaml

    data = read_yaml(path, "the profile", ProfileError)
    try:
        return DatasetProfile.from_dict(data, str(path))
    except ProfileError as exc:
        text = " ".join(str(exc).split())
        if len(text) <= MAX_ERROR_CHARS:
            raise
        raise ProfileError(text[: MAX_ERROR_CHARS - 3] + "...") from exc


def legacy_profile() -> DatasetProfile:
    """The profile of files written before profiles existed: all were SemanticKITTI's."""
    return _builtin(LEGACY_PROFILE)


def profile_of_record(record: Mapping[str, Any] | None, source: str) -> DatasetProfile:
    """The profile stored in a checkpoint or run record; `legacy_profile()` when it holds none."""
    if not record:
        return legacy_profile()
    return DatasetProfile.from_dict(record, source)
