"""nuScenes' tables, read as they ship: which keyframe sweeps a scene holds and where their files are.

    ROOT/v1.0-mini/*.json                          the tables of one version
    ROOT/samples/LIDAR_TOP/<name>.pcd.bin          a sweep (`sample_data.filename`)
    ROOT/lidarseg/v1.0-mini/<token>_lidarseg.bin   its labels (`lidarseg.filename`, optional)
    ROOT/panoptic/v1.0-mini/<token>_panoptic.npz   its panoptic labels (`panoptic.filename`,
                                                   optional: nuScenes-panoptic)

A scene's keyframes are its samples in order (`scene.first_sample_token`, then each sample's
`next`); a sample's sweep is the keyframe `sample_data` record of the sensor channel (LIDAR_TOP),
found through `calibrated_sensor` and `sensor`; its labels are the `lidarseg` record with the
sweep's token, and its panoptic labels the `panoptic` record with that token. A panoptic file
is an npz of one array, `data`: a uint16 per point, 1000 x the point's general category index
(its lidarseg label) + its object's instance (numbered from 1 within a scene; 0 for stuff and for
points of no object). Every inconsistency is named by table, record and field. Torch-free.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from rangeret.dataset.fields import is_int
from rangeret.exceptions import DatasetError

#: The tables every version folder holds (the devkit loads all of them).
TABLES = (
    "category",
    "attribute",
    "visibility",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "map",
)
#: The tables this reader needs; `lidarseg` and `panoptic` too where the version has them.
NEEDED = ("category", "sensor", "calibrated_sensor", "scene", "sample", "sample_data")
#: The largest table read (v1.0-trainval's sample_data.json is about 1 GB).
MAX_TABLE_BYTES = 4 << 30


class TableError(DatasetError, ValueError):
    """A nuScenes tree whose tables cannot be read or do not agree; the message names the file."""


@dataclass(frozen=True)
class Keyframe:
    """One keyframe sweep of a scene: its sample, its sample_data token and its files, relative
    to ROOT (the label file is None where the version has no lidarseg record for it, the panoptic
    file None where it has no panoptic record)."""

    sample: str
    token: str
    filename: str
    label_filename: str | None
    panoptic_filename: str | None = None


@dataclass(frozen=True)
class NuScenesTables:
    """What one version's tables say about its scenes' keyframe sweeps."""

    root: Path
    version: str
    #: Scene name -> its keyframes in time order, scenes in the order of scene.json.
    scenes: Mapping[str, tuple[Keyframe, ...]]
    #: Category index -> name (`category.json`'s general classes, 0-31 for nuScenes-lidarseg).
    categories: Mapping[int, str]
    #: Whether the version ships lidarseg.json (the test split does not).
    has_lidarseg: bool
    #: Whether the version ships panoptic.json (nuScenes-panoptic).
    has_panoptic: bool = False

    @property
    def table_dir(self) -> Path:
        """The version's folder of tables."""
        return self.root / self.version


def version_folders(root: Path | str) -> list[str]:
    """The names of ROOT's folders that hold a version's tables (a `scene.json`), sorted."""
    root = Path(root)
    if not root.is_dir():
        raise TableError(f"{root} does not exist: expected a nuScenes tree there")
    with os.scandir(root) as it:
        return sorted(e.name for e in it if e.is_dir() and (Path(e.path) / "scene.json").is_file())


def find_version(root: Path | str, version: str | None = None) -> str:
    """The version to read: `version` when given (its folder must hold tables), else the one
    version folder ROOT holds; none or several is a TableError saying what to pass."""
    found = version_folders(root)
    if version is not None:
        if version not in found:
            held = f"; it holds {', '.join(found)}" if found else ""
            raise TableError(f"{Path(root) / version} holds no nuScenes tables (scene.json){held}")
        return version
    if not found:
        raise TableError(
            f"{root} holds no nuScenes version folder (such as v1.0-mini/ with scene.json)"
        )
    if len(found) > 1:
        raise TableError(f"{root} holds the versions {', '.join(found)}: choose one with --version")
    return found[0]


def read_tables(root: Path | str, version: str, channel: str = "LIDAR_TOP") -> NuScenesTables:
    """The keyframe sweeps of every scene of `version` under ROOT for the sensor `channel`;
    read once per process while the tables' files are unchanged."""
    root = Path(root).resolve()
    table_dir = root / version
    stamps = tuple(_stamp(table_dir / f"{name}.json") for name in (*NEEDED, "lidarseg", "panoptic"))
    return _read(root, version, channel, stamps)


def _stamp(path: Path) -> tuple[int, int] | None:
    try:
        stat = path.stat()
    except FileNotFoundError:
        return None
    return stat.st_mtime_ns, stat.st_size


@lru_cache(maxsize=4)
def _read(
    root: Path, version: str, channel: str, stamps: tuple[tuple[int, int] | None, ...]
) -> NuScenesTables:
    table_dir = root / version
    tables = {name: _load(table_dir, name) for name in NEEDED}
    has_lidarseg = (table_dir / "lidarseg.json").is_file()
    lidarseg = _index(table_dir, "lidarseg", _load(table_dir, "lidarseg")) if has_lidarseg else {}
    has_panoptic = (table_dir / "panoptic.json").is_file()
    panoptic = _label_files(table_dir, "panoptic") if has_panoptic else {}

    categories: dict[int, str] = {}
    for i, record in enumerate(tables["category"]):
        where = f"{table_dir / 'category.json'}: record {i}"
        name, index = _field(record, "name", str, where), record.get("index")
        if not is_int(index):
            raise TableError(
                f"{where} ({name}) has no integer index: use the category.json that comes with "
                "nuScenes-lidarseg"
            )
        categories[index] = name

    sensors = _index(table_dir, "sensor", tables["sensor"])
    calibrated = _index(table_dir, "calibrated_sensor", tables["calibrated_sensor"])
    samples = _index(table_dir, "sample", tables["sample"])
    sweeps: dict[str, dict[str, Any]] = {}
    for i, record in enumerate(tables["sample_data"]):
        where = f"{table_dir / 'sample_data.json'}: record {i}"
        if not _field(record, "is_key_frame", bool, where):
            continue
        cs = calibrated.get(_field(record, "calibrated_sensor_token", str, where))
        sensor = sensors.get(cs.get("sensor_token", "")) if cs is not None else None
        if cs is None or sensor is None:
            raise TableError(f"{where} names a calibrated sensor or sensor the tables do not hold")
        if sensor.get("channel") == channel:
            sweeps[_field(record, "sample_token", str, where)] = record

    scenes: dict[str, tuple[Keyframe, ...]] = {}
    for i, scene in enumerate(tables["scene"]):
        where = f"{table_dir / 'scene.json'}: record {i}"
        name = _field(scene, "name", str, where)
        token = _field(scene, "first_sample_token", str, where)
        expected = _field(scene, "nbr_samples", int, where)
        frames: list[Keyframe] = []
        while token:
            sample = samples.get(token)
            if sample is None or len(frames) > expected:
                raise TableError(
                    f"{where} ({name}): its chain of samples breaks at {token!r} after "
                    f"{len(frames)} of its {expected} samples"
                )
            sweep = sweeps.get(token)
            if sweep is None:
                raise TableError(f"{where} ({name}): sample {token} has no {channel} keyframe")
            sd = sweep["token"]
            label = lidarseg.get(sd)
            frames.append(
                Keyframe(
                    token,
                    sd,
                    _field(sweep, "filename", str, f"sample_data {sd}"),
                    None if label is None else _field(label, "filename", str, f"lidarseg {sd}"),
                    panoptic.get(sd),
                )
            )
            token = sample.get("next", "")
        if len(frames) != expected:
            raise TableError(
                f"{where} ({name}) says {expected} samples but its chain holds {len(frames)}"
            )
        if name in scenes:
            raise TableError(f"{where}: scene {name} is listed twice")
        scenes[name] = tuple(frames)
    return NuScenesTables(root, version, scenes, categories, has_lidarseg, has_panoptic)


def _load(table_dir: Path, name: str) -> list[dict[str, Any]]:
    """A table: a JSON list of records (objects); anything else is a TableError naming it."""
    path = table_dir / f"{name}.json"
    try:
        if path.stat().st_size > MAX_TABLE_BYTES:
            raise TableError(f"{path} is larger than {MAX_TABLE_BYTES >> 30} GiB")
        with open(path, "rb") as f:
            data = json.load(f)
    except FileNotFoundError:
        raise TableError(
            f"{path} is missing (every nuScenes version holds a {name} table)"
        ) from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise TableError(f"{path} is not a JSON table: {exc}") from exc
    if not isinstance(data, list) or not all(isinstance(r, dict) for r in data):
        raise TableError(f"{path} must hold a list of records")
    return data


def _index(table_dir: Path, name: str, records: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """A table's records by token; a record without one is a TableError naming it."""
    out: dict[str, dict[str, Any]] = {}
    for i, record in enumerate(records):
        out[_field(record, "token", str, f"{table_dir / (name + '.json')}: record {i}")] = record
    return out


def _label_files(table_dir: Path, name: str) -> dict[str, str]:
    """A label table's file names by token, every record checked; a record without a string
    token or filename is a TableError naming the table, the record and the field."""
    out: dict[str, str] = {}
    for i, record in enumerate(_load(table_dir, name)):
        where = f"{table_dir / (name + '.json')}: record {i}"
        token = _field(record, "token", str, where)
        if token in out:
            raise TableError(f"{where}: sample_data {token} has a second {name} record")
        out[token] = _field(record, "filename", str, where)
    return out


def _field(record: Mapping[str, Any], key: str, kind: type, where: str) -> Any:
    value = record.get(key)
    if not (is_int(value) if kind is int else isinstance(value, kind)):
        raise TableError(f"{where} has no {kind.__name__} {key!r} (got {value!r})")
    return value
