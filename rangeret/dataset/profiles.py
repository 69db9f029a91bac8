"""Dataset profiles: everything that differs between datasets and sensors, held as data.

A profile gathers the sensor's projection (resolution, field of view, input normalisation, where a
point's row comes from), the point record of its scan files, its label configuration, the kNN
voting rule, its folder layout and its splits. Three are built in with the release's values
(`semantickitti`, the default, `semantic-poss` and `pandaset`, in `data/profiles/`); a YAML file
with exactly the fields that `rangeret profile show NAME` prints describes any other sensor.
Torch-free.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path
from typing import Any

from rangeret import DATA_DIR
from rangeret.dataset.fields import Fields
from rangeret.dataset.labels import LabelConfig, LabelConfigError, parse_label_config
from rangeret.dataset.layout import SequenceLayout
from rangeret.dataset.projection import ROW_SOURCES, ProjectionConfig
from rangeret.exceptions import ConfigError
from rangeret.io.scans import PointRecord

PROFILES_DIR = DATA_DIR / "profiles"
#: The profile the command line and the gateway's settings apply when none is named.
DEFAULT_PROFILE = "semantickitti"
#: Files written before profiles existed (checkpoints, run records) were all SemanticKITTI's.
LEGACY_PROFILE = "semantickitti"
BUILTIN_PROFILES = ("semantickitti", "semantic-poss", "pandaset")


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
    layout: SequenceLayout

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

    def with_overrides(
        self,
        height: int | None = None,
        width: int | None = None,
        fov_up: float | None = None,
        fov_down: float | None = None,
        labels: LabelConfig | None = None,
    ) -> DatasetProfile:
        """The profile with explicit command-line values in place of its own (None keeps them)."""
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
        return replace(self, projection=projection, labels=labels or self.labels)

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
        }

    @classmethod
    def from_dict(cls, data: Any, source: str = "profile") -> DatasetProfile:
        """A profile from `to_dict()`'s form; a wrong, missing or extra field is a ProfileError
        naming it (as `source: field.path: problem`)."""
        f = Fields(data, source, error=ProfileError, kind="profile field")
        sensor = f.section("sensor", _SENSOR_KEYS)
        points = f.section("points", ("fields",))
        layout = f.section("layout", ("sequence_folders", "id_digits"))
        knn = f.section("knn", ("votes_from",))
        labels = f.section("labels", ("unlabeled_class", "classes", "raw_labels"))
        splits = f.get("splits", dict)
        f.finish(_TOP_KEYS)

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
        if row == "laser_id" and "laser_id" not in record.fields[4:]:
            points.fail("fields", "must end with laser_id when sensor.row is laser_id")

        folders = tuple(layout.strings("sequence_folders"))
        if not folders:
            layout.fail("sequence_folders", "must name at least one folder")
        sequence_layout = SequenceLayout(folders, layout.integer("id_digits", 1, 8))

        try:
            label_config = parse_label_config(
                labels.data,
                source,
                field="labels",
                splits=splits,
                normalise=sequence_layout.normalise,
            )
        except LabelConfigError as exc:
            raise ProfileError(str(exc)) from exc
        votes_from = knn.integer("votes_from", 0, label_config.num_classes - 1)
        name = f.get("name", str)
        if not name.strip():
            f.fail("name", "must not be empty")
        return cls(
            name=name,
            description=f.get("description", str),
            projection=projection,
            points=record,
            labels=label_config,
            knn=KnnVote(votes_from),
            layout=sequence_layout,
        )

    def to_yaml(self) -> str:
        """The profile as YAML text that `load_profile` reads back unchanged."""
        import yaml

        return yaml.safe_dump(self.to_dict(), sort_keys=False, allow_unicode=True, width=100)


_TOP_KEYS = ("name", "description", "sensor", "points", "layout", "knn", "labels", "splits")
_SENSOR_KEYS = ("height", "width", "fov_up", "fov_down", "row", "means", "stds")


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
    if not path.is_file():
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
    from rangeret.io.bounded_yaml import YamlLimitError, load_yaml

    try:
        data = load_yaml(path)
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"cannot read the profile {path}: {exc}") from exc
    except YamlLimitError as exc:
        raise ProfileError(str(exc)) from exc
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
