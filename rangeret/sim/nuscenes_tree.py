"""A simulated nuScenes tree in the real layout: the version's 13 tables, lidarseg.json and
panoptic.json, a map mask, keyframe sweeps (`.pcd.bin`) and their label files, as nuScenes'
devkit loads them.

    ROOT/v1.0-mini/{category,attribute,visibility,instance,sensor,calibrated_sensor,ego_pose,
                    log,scene,sample,sample_data,sample_annotation,map,lidarseg,panoptic}.json
    ROOT/maps/<token>.png
    ROOT/samples/LIDAR_TOP/<log>__LIDAR_TOP__<timestamp>.pcd.bin
    ROOT/lidarseg/v1.0-mini/<sample_data token>_lidarseg.bin
    ROOT/panoptic/v1.0-mini/<sample_data token>_panoptic.npz

Each scene drives along its own street and has one keyframe every half second (nuScenes annotates
at 2 Hz); only keyframes are written (no intermediate sweeps, no cameras, no boxes). Tokens are
derived from the seed and the scene's name, so the same seed writes the same bytes.

A labelled keyframe's panoptic file holds, per point, 1000 x its lidarseg label + its instance:
points of a thing class (the profile's `things`) carry their simulated object, numbered from 1 within
the scene in the order the keyframes first see them (so an object keeps its number from keyframe
to keyframe, as nuScenes-panoptic numbers a scene's annotated instances); stuff points and points
of no object carry 0. With no boxes the instance table stays empty, as nothing refers to it.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import zlib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rangeret.dataset.labels import SEMANTIC_MASK
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.table_layout import LIDARSEG_LABELS
from rangeret.io.atomic import atomic_write_bytes
from rangeret.io.panoptic_labels import THOUSANDS, write_panoptic_npz
from rangeret.io.scans import write_scan
from rangeret.sim.dataset import check_profile, sequence_scans
from rangeret.sim.raycast import SensorConfig, SimulationError

#: The version folder written.
VERSION = "v1.0-mini"
#: Seconds between two keyframes.
KEYFRAME_PERIOD = 0.5
#: The first keyframe's timestamp (microseconds), a day of the mini split's logs.
START_US = 1_531_883_530_449_377
#: Where LIDAR_TOP sits on the ego vehicle (m), as nuScenes' calibration puts it.
LIDAR_TRANSLATION = (0.985793, 0.0, 1.84019)
#: Columns the HDL-32E returns per turn at 20 Hz (about 34,700 points a sweep over 32 beams).
AZIMUTH_STEPS = 1086
#: Scenes written when none are asked for: two of mini_train and both of mini_val.
DEFAULT_SCENES = {"scene-0061": 3, "scene-0553": 2, "scene-0103": 3, "scene-0916": 2}


def _token(*parts: object) -> str:
    """A 32-hex-digit token, like nuScenes', from the seed and names."""
    return hashlib.sha256("/".join(map(str, parts)).encode()).hexdigest()[:32]


def _png(width: int, height: int, value: int) -> bytes:
    """A uniform 8-bit greyscale PNG."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    rows = b"".join(b"\x00" + bytes([value]) * width for _ in range(height))
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


def _write_json(path: Path, records: Any) -> None:
    atomic_write_bytes(path, (json.dumps(records, indent=0) + "\n").encode())


def thing_categories(profile: DatasetProfile) -> np.ndarray:
    """(65536,) bool: whether a raw id (a general category index) is in one of the profile's
    thing classes."""
    labels = profile.labels
    lut = np.zeros(SEMANTIC_MASK + 1, dtype=bool)
    for raw, cls in labels.raw_to_class.items():
        lut[raw] = cls in profile.things
    return lut


def panoptic_values(
    raw: np.ndarray, things: np.ndarray, instances: dict[int, int], scene: str
) -> np.ndarray:
    """A keyframe's panoptic values, uint16 per point, from its labels (raw id | object << 16):
    1000 x raw id + the scene's number of the point's object where the raw id is a thing
    (`things`), else + 0. `instances` maps the scene's objects to their numbers and gains those
    this keyframe sees first, numbered on in ascending object order."""
    raw = np.asarray(raw, dtype=np.uint32)
    semantic = raw & np.uint32(SEMANTIC_MASK)
    objects = raw >> np.uint32(16)
    thing = things[semantic] & (objects > 0)
    seen, inverse = np.unique(objects[thing], return_inverse=True)
    for obj in seen.tolist():
        instances.setdefault(obj, len(instances) + 1)
    if len(instances) >= THOUSANDS.multiplier:
        raise SimulationError(
            f"{scene} holds {len(instances)} objects, more than a panoptic value numbers "
            f"(at most {THOUSANDS.multiplier - 1} a scene)"
        )
    numbers = np.array([instances[obj] for obj in seen.tolist()], dtype=np.uint32)
    instance = np.zeros(raw.shape, dtype=np.uint32)
    instance[thing] = numbers[inverse.ravel()]
    values = semantic * np.uint32(THOUSANDS.multiplier) + instance
    if values.size and values.max() > np.iinfo(np.uint16).max:
        raise SimulationError(f"{scene}: raw id {semantic.max()} does not fit a panoptic value")
    return values.astype(np.uint16)


def simulate_nuscenes(
    root: str | os.PathLike[str],
    scenes: Mapping[str, int] | None = None,
    labelled: Iterable[str] | bool = True,
    sensor: SensorConfig | None = None,
    seed: int = 0,
    progress: bool = False,
    *,
    profile: DatasetProfile,
    version: str = VERSION,
    panoptic: bool = True,
) -> int:
    """Write a simulated tree of `version` (v1.0-mini) under `root` and return the number of
    keyframes.

    `scenes` maps a scene name to its number of keyframes (`DEFAULT_SCENES` when None);
    `labelled` says which scenes get lidarseg records and label files (True: all, False: none,
    so no lidarseg.json is written, as for the test split), and, with `panoptic`, panoptic
    records and files too (none and no panoptic.json without it). The profile must read tables;
    the sensor defaults to the profile's with the HDL-32E's `AZIMUTH_STEPS`.
    """
    if profile.layout.folders is not None:
        raise SimulationError(f"profile {profile.name} does not read a version's tables")
    sensor = sensor or SensorConfig.for_profile(profile, azimuth_steps=AZIMUTH_STEPS)
    check_profile(profile, sensor)
    counts = dict(DEFAULT_SCENES if scenes is None else scenes)
    if not counts or any(n < 1 for n in counts.values()):
        raise SimulationError(f"every scene needs at least one keyframe, got {counts}")
    if isinstance(labelled, bool):
        with_labels = set(counts) if labelled else set()
    else:
        with_labels = set(labelled)
        unknown = sorted(with_labels - set(counts))
        if unknown:
            raise SimulationError(f"labelled scenes {unknown} are not among the scenes")

    root = Path(root)
    tables: dict[str, list[dict[str, Any]]] = {
        name: []
        for name in (
            "attribute",
            "visibility",
            "instance",
            "sample_annotation",
            "ego_pose",
            "log",
            "scene",
            "sample",
            "sample_data",
            "lidarseg",
            "panoptic",
        )
    }
    things = thing_categories(profile)
    tables["category"] = [
        {
            "token": _token(seed, "category", raw),
            "name": name,
            "description": f"nuScenes-lidarseg general class {raw}",
            "index": raw,
        }
        for raw, name in sorted(profile.labels.raw_names.items())
    ]
    sensor_token = _token(seed, "sensor", "LIDAR_TOP")
    tables["sensor"] = [{"token": sensor_token, "channel": "LIDAR_TOP", "modality": "lidar"}]
    calibrated_token = _token(seed, "calibrated_sensor", "LIDAR_TOP")
    tables["calibrated_sensor"] = [
        {
            "token": calibrated_token,
            "sensor_token": sensor_token,
            "translation": list(LIDAR_TRANSLATION),
            "rotation": [0.7071067811865476, 0.0, 0.0, 0.7071067811865476],
            "camera_intrinsic": [],
        }
    ]
    map_token = _token(seed, "map")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(counts.values()), unit="sweep", desc="simulating")
    written = 0
    time_us = START_US
    try:
        for scene_name, n in counts.items():
            log_token = _token(seed, "log", scene_name)
            logfile = f"n015-2018-07-18-11-07-57+0800-{scene_name}"
            tables["log"].append(
                {
                    "token": log_token,
                    "logfile": logfile,
                    "vehicle": "n015",
                    "date_captured": "2018-07-18",
                    "location": "singapore-onenorth",
                }
            )
            samples = [_token(seed, "sample", scene_name, k) for k in range(n)]
            sweeps = [_token(seed, "sample_data", scene_name, k) for k in range(n)]
            scene_token = _token(seed, "scene", scene_name)
            tables["scene"].append(
                {
                    "token": scene_token,
                    "log_token": log_token,
                    "nbr_samples": n,
                    "first_sample_token": samples[0],
                    "last_sample_token": samples[-1],
                    "name": scene_name,
                    "description": "simulated street",
                }
            )
            scans = sequence_scans(
                scene_name, n, sensor, seed, profile=profile, period=KEYFRAME_PERIOD
            )
            instances: dict[int, int] = {}
            for k, (points, raw, x) in enumerate(scans):
                stamp = time_us + int(k * KEYFRAME_PERIOD * 1e6)
                sd = sweeps[k]
                filename = f"samples/LIDAR_TOP/{logfile}__LIDAR_TOP__{stamp}.pcd.bin"
                write_scan(root / filename, points, record=profile.points)
                pose_token = _token(seed, "ego_pose", scene_name, k)
                tables["ego_pose"].append(
                    {
                        "token": pose_token,
                        "timestamp": stamp,
                        "rotation": [1.0, 0.0, 0.0, 0.0],
                        "translation": [float(x), 0.0, 0.0],
                    }
                )
                tables["sample"].append(
                    {
                        "token": samples[k],
                        "timestamp": stamp,
                        "prev": samples[k - 1] if k else "",
                        "next": samples[k + 1] if k + 1 < n else "",
                        "scene_token": scene_token,
                    }
                )
                tables["sample_data"].append(
                    {
                        "token": sd,
                        "sample_token": samples[k],
                        "ego_pose_token": pose_token,
                        "calibrated_sensor_token": calibrated_token,
                        "timestamp": stamp,
                        "fileformat": "pcd",
                        "is_key_frame": True,
                        "height": 0,
                        "width": 0,
                        "filename": filename,
                        "prev": sweeps[k - 1] if k else "",
                        "next": sweeps[k + 1] if k + 1 < n else "",
                    }
                )
                if scene_name in with_labels:
                    label_name = f"lidarseg/{version}/{sd}_lidarseg.bin"
                    LIDARSEG_LABELS.write(root / label_name, raw & np.uint32(SEMANTIC_MASK))
                    tables["lidarseg"].append(
                        {"token": sd, "sample_data_token": sd, "filename": label_name}
                    )
                    if panoptic:
                        panoptic_name = f"panoptic/{version}/{sd}_panoptic.npz"
                        values = panoptic_values(raw, things, instances, scene_name)
                        write_panoptic_npz(root / panoptic_name, values)
                        tables["panoptic"].append(
                            {"token": sd, "sample_data_token": sd, "filename": panoptic_name}
                        )
                written += 1
                if bar is not None:
                    bar.update(1)
            time_us += int((n + 10) * KEYFRAME_PERIOD * 1e6)
        logs = [record["token"] for record in tables["log"]]
        mask = f"maps/{map_token}.png"
        atomic_write_bytes(root / mask, _png(8, 8, 255))
        tables["map"] = [
            {"token": map_token, "log_tokens": logs, "category": "semantic_prior", "filename": mask}
        ]
        if not with_labels:
            del tables["lidarseg"]
        if not (with_labels and panoptic):
            del tables["panoptic"]
        for name, records in tables.items():
            _write_json(root / version / f"{name}.json", records)
    finally:
        if bar is not None:
            bar.close()
    return written
