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

The tables are data, never instructions: each is read within the bounds of
`rangeret.dataset.json_tables`; a sweep's token, which names its prediction files, must be 32
lowercase hexadecimal digits as nuScenes writes them (`TOKEN`); a file a table names must be a
relative path inside the tree (no `..`, not absolute); and a scene's chain of samples stops at a
repeated sample or past the samples the tables hold, whatever its `nbr_samples` says.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from rangeret.dataset.fields import is_int
from rangeret.dataset.json_tables import TableError, read_table

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
#: A token as nuScenes writes them: a UUID's 32 hexadecimal digits, lowercase, without dashes.
TOKEN = re.compile(r"^[0-9a-f]{32}$")
#: A scene's name: `scene-0103`, or any name of letters, digits, `.`, `_` and `-`.
SCENE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")

__all__ = ["TOKEN", "Keyframe", "NuScenesTables", "TableError", "find_version", "read_tables"]


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
    tables = {name: _load(table_dir, name) for name in NEEDED if name != "sample_data"}
    has_lidarseg = (table_dir / "lidarseg.json").exists()
    lidarseg = _label_files(table_dir, "lidarseg") if has_lidarseg else {}
    has_panoptic = (table_dir / "panoptic.json").exists()
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
    path = table_dir / "sample_data.json"

    def keyframe(i: int, record: dict[str, Any]) -> None:
        """Note record i of sample_data when it is a keyframe of `channel` (nothing is kept)."""
        where = f"{path}: record {i}"
        if not _field(record, "is_key_frame", bool, where):
            return
        cs = calibrated.get(_field(record, "calibrated_sensor_token", str, where))
        sensor = sensors.get(cs.get("sensor_token", "")) if cs is not None else None
        if cs is None or sensor is None:
            raise TableError(f"{where} names a calibrated sensor or sensor the tables do not hold")
        if sensor.get("channel") == channel:
            token = _token(record, where)
            sweeps[_field(record, "sample_token", str, where)] = {
                "token": token,
                "filename": _file(record, "filename", where),
            }

    read_table(path, "sample_data", keyframe)
    scenes: dict[str, tuple[Keyframe, ...]] = {}
    for i, scene in enumerate(tables["scene"]):
        where = f"{table_dir / 'scene.json'}: record {i}"
        name = _field(scene, "name", str, where)
        if not SCENE_NAME.match(name):
            raise TableError(
                f"{where} has the name {name[:100]!r}: a scene's name is letters, digits, '.', "
                "'_' and '-' (such as scene-0103)"
            )
        if name in scenes:
            raise TableError(f"{where}: scene {name} is listed twice")
        scenes[name] = _chain(scene, where, name, samples, sweeps, lidarseg, panoptic, channel)
    return NuScenesTables(root, version, scenes, categories, has_lidarseg, has_panoptic)


def _chain(
    scene: Mapping[str, Any],
    where: str,
    name: str,
    samples: Mapping[str, Mapping[str, Any]],
    sweeps: Mapping[str, Mapping[str, str]],
    lidarseg: Mapping[str, str],
    panoptic: Mapping[str, str],
    channel: str,
) -> tuple[Keyframe, ...]:
    """A scene's keyframes, from its first sample along each sample's `next`. The walk stops at
    a sample it has seen (a cycle) and never takes more steps than the tables hold samples; a
    chain of another length than `nbr_samples` is refused, after the walk."""
    token = _field(scene, "first_sample_token", str, where)
    expected = _field(scene, "nbr_samples", int, where)
    seen: set[str] = set()
    frames: list[Keyframe] = []
    while token:
        if token in seen:
            raise TableError(
                f"{where} ({name}): its chain of samples returns to sample {token[:64]!r} after "
                f"{len(frames)} samples (a cycle in sample.json's next)"
            )
        sample = samples.get(token)
        if sample is None:
            raise TableError(
                f"{where} ({name}): its chain of samples breaks at {token[:64]!r} after "
                f"{len(frames)} of its {expected} samples"
            )
        seen.add(token)
        sweep = sweeps.get(token)
        if sweep is None:
            raise TableError(f"{where} ({name}): sample {token} has no {channel} keyframe")
        sd = sweep["token"]
        frames.append(Keyframe(token, sd, sweep["filename"], lidarseg.get(sd), panoptic.get(sd)))
        token = sample.get("next", "")
        if not isinstance(token, str):
            raise TableError(f"sample {frames[-1].sample} has no str 'next' (got {token!r})")
    if len(frames) != expected:
        raise TableError(
            f"{where} ({name}) says {expected} samples but its chain holds {len(frames)}"
        )
    return tuple(frames)


def _load(table_dir: Path, name: str) -> list[dict[str, Any]]:
    """A table's records, read within bounds (`rangeret.dataset.json_tables`)."""
    return read_table(table_dir / f"{name}.json", name)


def _index(table_dir: Path, name: str, records: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """A table's records by token; a record without one is a TableError naming it."""
    out: dict[str, dict[str, Any]] = {}
    for i, record in enumerate(records):
        out[_field(record, "token", str, f"{table_dir / (name + '.json')}: record {i}")] = record
    return out


def _label_files(table_dir: Path, name: str) -> dict[str, str]:
    """A label table's file names by sweep token, every record checked; a record without a
    sweep token or a file inside the tree is a TableError naming the table, record and field."""
    out: dict[str, str] = {}
    path = table_dir / f"{name}.json"

    def note(i: int, record: dict[str, Any]) -> None:
        where = f"{path}: record {i}"
        token = _token(record, where)
        if token in out:
            raise TableError(f"{where}: sample_data {token} has a second {name} record")
        out[token] = _file(record, "filename", where)

    read_table(path, name, note)
    return out


def _token(record: Mapping[str, Any], where: str) -> str:
    """A record's `token`, which names files: 32 lowercase hexadecimal digits (`TOKEN`)."""
    token = _field(record, "token", str, where)
    if not TOKEN.match(token):
        raise TableError(
            f"{where} has the token {token[:100]!r}: a token is 32 lowercase hexadecimal "
            "digits, as nuScenes writes them"
        )
    return token


def _file(record: Mapping[str, Any], key: str, where: str) -> str:
    """A file a record names, relative to the tree's root: a path without `..`, `.` or empty
    parts, not absolute, so that it stays inside the tree."""
    name = _field(record, key, str, where)
    parts = name.split("/")
    if not name or "\\" in name or "\0" in name or any(p in ("", ".", "..") for p in parts):
        raise TableError(
            f"{where} names the file {name[:200]!r} in {key!r}: a table's file must be a "
            "relative path inside the tree (no '..', not absolute)"
        )
    return name


def _field(record: Mapping[str, Any], key: str, kind: type, where: str) -> Any:
    value = record.get(key)
    if not (is_int(value) if kind is int else isinstance(value, kind)):
        raise TableError(f"{where} has no {kind.__name__} {key!r} (got {value!r})")
    return value
