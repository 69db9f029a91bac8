"""Dataset profiles: everything that differs between datasets and sensors, held as data.

A profile gathers the sensor's projection (resolution, field of view, input normalisation, where a
point's row comes from), the point record of its scan files, its label configuration, the kNN
voting rule, its folder layout and its splits. Three are built in with the release's values
(`semantickitti`, the default, `semantic-poss` and `pandaset`, in `data/profiles/`); a YAML file
with exactly the fields that `rangeret profile show NAME` prints describes any other sensor.
Torch-free.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path
from typing import Any, NoReturn

from rangeret import DATA_DIR
from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.layout import SequenceLayout
from rangeret.dataset.projection import ROW_SOURCES, ProjectionConfig
from rangeret.exceptions import ConfigError
from rangeret.io.scans import PointRecord

PROFILES_DIR = DATA_DIR / "profiles"
DEFAULT_PROFILE = "semantickitti"
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
        f = _Fields(data, source)
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

        classes = labels.records("classes", ("name", "raw_id", "ignored"))
        raw_labels = labels.records("raw_labels", ("id", "name", "class", "bgr", "frequency"))
        num_classes = len(classes)
        if num_classes < 2:
            labels.fail("classes", f"must list at least 2 classes, got {num_classes}")
        unlabeled = labels.integer("unlabeled_class", 0, num_classes - 1)
        votes_from = knn.integer("votes_from", 0, num_classes - 1)
        label_config = _label_config(
            labels, classes, raw_labels, unlabeled, splits, sequence_layout
        )
        name = f.value("name", str)
        if not name.strip():
            f.fail("name", "must not be empty")
        return cls(
            name=name,
            description=f.value("description", str),
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
    (`semantickitti`). Anything wrong is a ProfileError naming the file and the field."""
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


def profile_of_record(record: Mapping[str, Any] | None, source: str) -> DatasetProfile:
    """The profile stored in a checkpoint or run record; the default one when it holds none
    (files written before profiles existed were all SemanticKITTI's)."""
    if not record:
        return load_profile(None)
    return DatasetProfile.from_dict(record, source)


def _label_config(
    labels: _Fields,
    classes: list[dict[str, Any]],
    raw_labels: list[dict[str, Any]],
    unlabeled: int,
    splits: Mapping[str, Any],
    layout: SequenceLayout,
) -> LabelConfig:
    """The label configuration of a profile's `labels` and `splits` sections."""
    for i, c in enumerate(classes):
        if not isinstance(c["name"], str) or not isinstance(c["ignored"], bool):
            labels.fail(f"classes[{i}]", "needs a text name and a true/false ignored")
    raw_to_class: dict[int, int] = {}
    for i, r in enumerate(raw_labels):
        raw, cls = r["id"], r["class"]
        if not _is_int(raw) or not 0 <= raw <= 0xFFFF:
            labels.fail(f"raw_labels[{i}].id", f"must be a raw id 0..65535, got {raw!r}")
        if not _is_int(cls) or not 0 <= cls < len(classes):
            labels.fail(
                f"raw_labels[{i}].class", f"must be a class 0..{len(classes) - 1}, got {cls!r}"
            )
        if raw in raw_to_class:
            labels.fail(f"raw_labels[{i}].id", f"raw id {raw} is listed twice")
        bgr = r["bgr"]
        if not (
            isinstance(bgr, list)
            and len(bgr) == 3
            and all(_is_int(v) and 0 <= v <= 255 for v in bgr)
        ):
            labels.fail(f"raw_labels[{i}].bgr", f"must be three integers 0..255, got {bgr!r}")
        if not isinstance(r["frequency"], int | float) or isinstance(r["frequency"], bool):
            labels.fail(f"raw_labels[{i}].frequency", f"must be a number, got {r['frequency']!r}")
        raw_to_class[raw] = cls
    class_raw = [c["raw_id"] for c in classes]
    for i, raw in enumerate(class_raw):
        if raw not in raw_to_class:
            labels.fail(f"classes[{i}].raw_id", f"raw id {raw!r} is not among raw_labels")
        if raw_to_class[raw] != i:
            labels.fail(
                f"classes[{i}].raw_id",
                f"raw id {raw} maps to class {raw_to_class[raw]}, not back to class {i}",
            )
    split_ids: dict[str, tuple[str, ...]] = {}
    for name, ids in splits.items():
        if not isinstance(ids, list) or not all(
            isinstance(s, str | int) and not isinstance(s, bool) for s in ids
        ):
            raise ProfileError(f"{labels.source}: splits.{name}: must be a list of sequence ids")
        split_ids[str(name)] = tuple(layout.normalise(s) for s in ids)
    try:
        return LabelConfig(
            class_names=tuple(c["name"] for c in classes),
            class_raw_ids=tuple(class_raw),
            ignored=tuple(c["ignored"] for c in classes),
            raw_names={r["id"]: str(r["name"]) for r in raw_labels},
            raw_to_class=raw_to_class,
            raw_bgr={r["id"]: tuple(r["bgr"]) for r in raw_labels},
            raw_frequency={r["id"]: float(r["frequency"]) for r in raw_labels},
            splits=split_ids,
            unlabeled_class=unlabeled,
        )
    except ValueError as exc:
        raise ProfileError(f"{labels.source}: labels: {exc}") from exc


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


class _Fields:
    """One mapping of a profile being read, that names the field path in every error."""

    def __init__(self, data: Any, source: str, path: str = "") -> None:
        if not isinstance(data, Mapping):
            where = f"{path}: " if path else ""
            raise ProfileError(
                f"{source}: {where}must be a mapping of fields, got {type(data).__name__}"
            )
        self.data, self.source, self.path = data, source, path

    def _name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def fail(self, key: str, problem: str) -> NoReturn:
        raise ProfileError(f"{self.source}: {self._name(key)}: {problem}")

    def finish(self, keys: Sequence[str]) -> None:
        """Every expected field is there, and no other."""
        extra = sorted(str(k) for k in self.data if k not in keys)
        if extra:
            self.fail(extra[0], f"is not a profile field (expected: {', '.join(keys)})")
        missing = [k for k in keys if k not in self.data]
        if missing:
            self.fail(missing[0], "is missing")

    def get(self, key: str, kind: type) -> Any:
        if key not in self.data:
            self.fail(key, "is missing")
        value = self.data[key]
        if not isinstance(value, kind):
            self.fail(key, f"must be a {kind.__name__}, got {value!r}")
        return value

    def value(self, key: str, kind: type) -> Any:
        return self.get(key, kind)

    def section(self, key: str, keys: Sequence[str]) -> _Fields:
        if key not in self.data:
            self.fail(key, "is missing")
        section = _Fields(self.data[key], self.source, self._name(key))
        section.finish(keys)
        return section

    def integer(self, key: str, low: int, high: int | None = None) -> int:
        value = self.data[key]
        if not _is_int(value) or value < low or (high is not None and value > high):
            bound = f"{low}..{high}" if high is not None else f"at least {low}"
            self.fail(key, f"must be an integer {bound}, got {value!r}")
        return value

    def number(self, key: str) -> float:
        value = self.data[key]
        if not isinstance(value, int | float) or isinstance(value, bool):
            self.fail(key, f"must be a number, got {value!r}")
        return float(value)

    def numbers(self, key: str, count: int) -> tuple[float, ...]:
        value = self.data[key]
        if (
            not isinstance(value, list)
            or len(value) != count
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        ):
            self.fail(key, f"must be a list of {count} numbers, got {value!r}")
        return tuple(float(v) for v in value)

    def strings(self, key: str) -> list[str]:
        value = self.data[key]
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            self.fail(key, f"must be a list of names, got {value!r}")
        return value

    def choice(self, key: str, choices: Sequence[str]) -> str:
        value = self.data[key]
        if value not in choices:
            self.fail(key, f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    def records(self, key: str, keys: Sequence[str]) -> list[dict[str, Any]]:
        value = self.data[key]
        if not isinstance(value, list):
            self.fail(key, f"must be a list, got {value!r}")
        for i, item in enumerate(value):
            _Fields(item, self.source, f"{self._name(key)}[{i}]").finish(keys)
        return value
