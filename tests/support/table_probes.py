"""Hostile nuScenes tables for the tests of both front doors (command line and gateway): each
probe rewrites one table of a simulated tree's files, as an adversary could ship them."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

VERSION = "v1.0-mini"
#: The name of the file a traversal token would make, were it used as a path.
ESCAPED = "escaped_lidarseg.bin"

#: A probe: the tree's files by path -> the hostile files (tables rewritten).
Probe = Callable[[dict[str, bytes]], dict[str, bytes]]


def _table(files: dict[str, bytes], name: str) -> list[dict]:
    return json.loads(files[f"{VERSION}/{name}.json"])


def _with(files: dict[str, bytes], name: str, data: list | bytes) -> dict[str, bytes]:
    raw = data if isinstance(data, bytes) else json.dumps(data).encode()
    return {**files, f"{VERSION}/{name}.json": raw}


def _first_keyframe(files: dict[str, bytes]) -> tuple[list[dict], int]:
    records = _table(files, "sample_data")
    return records, next(i for i, r in enumerate(records) if r["is_key_frame"])


def traversal_token(files: dict[str, bytes]) -> dict[str, bytes]:
    """A keyframe sweep whose token climbs out of any folder its predictions go to."""
    records, i = _first_keyframe(files)
    records[i]["token"] = "../../../../escaped"
    return _with(files, "sample_data", records)


def absolute_token(files: dict[str, bytes]) -> dict[str, bytes]:
    """A keyframe sweep whose token is an absolute path."""
    records, i = _first_keyframe(files)
    records[i]["token"] = "/tmp/escaped"
    return _with(files, "sample_data", records)


def absolute_sweep(files: dict[str, bytes]) -> dict[str, bytes]:
    """A keyframe whose sweep file is /etc/passwd."""
    records, i = _first_keyframe(files)
    records[i]["filename"] = "/etc/passwd"
    return _with(files, "sample_data", records)


def climbing_label(files: dict[str, bytes]) -> dict[str, bytes]:
    """A label record whose file climbs out of the tree."""
    records = _table(files, "lidarseg")
    records[0]["filename"] = f"lidarseg/../../../{records[0]['token']}_lidarseg.bin"
    return _with(files, "lidarseg", records)


def cycle(files: dict[str, bytes]) -> dict[str, bytes]:
    """A scene whose first sample is its own next, claiming 10^15 samples."""
    scenes, samples = _table(files, "scene"), _table(files, "sample")
    first = scenes[0]["first_sample_token"]
    for sample in samples:
        if sample["token"] == first:
            sample["next"] = first
    scenes[0]["nbr_samples"] = 10**15
    return _with(_with(files, "sample", samples), "scene", scenes)


def empty_objects(name: str, size: int) -> Probe:
    """Table `name` as `size` bytes of empty objects (small once compressed)."""

    def probe(files: dict[str, bytes]) -> dict[str, bytes]:
        count = (size - 2) // 3
        return _with(files, name, b"[" + b"{}," * (count - 1) + b"{}]")

    return probe


def deep(files: dict[str, bytes]) -> dict[str, bytes]:
    """scene.json holding one record nested 100,000 deep (few values per byte)."""
    depth = 100_000
    nested = b'[{"scene":' + b'{"aaaa":' * depth + b"1" + b"}" * depth + b"}]"
    return _with(files, "scene", nested)


PROBES: dict[str, tuple[Probe, str]] = {
    "traversal token": (traversal_token, "has the token '../../../../escaped'"),
    "absolute token": (absolute_token, "has the token '/tmp/escaped'"),
    "absolute sweep": (absolute_sweep, "names the file '/etc/passwd' in 'filename'"),
    "climbing label": (climbing_label, "lidarseg.json: record 0 names the file"),
    "cycle": (cycle, "its chain of samples returns to sample"),
    "deep": (deep, "nests deeper than a JSON table may"),
    "huge category": (empty_objects("category", 120 << 20), "category.json is 125,829,"),
    "huge calibrated_sensor": (
        empty_objects("calibrated_sensor", 120 << 20),
        "calibrated_sensor.json is 125,829,",
    ),
}


def tree_files(root: Path) -> dict[str, bytes]:
    """A tree's files by their path in it (its maps left out)."""
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and not p.relative_to(root).as_posix().startswith("maps/")
    }


def write_files(root: Path, files: dict[str, bytes]) -> Path:
    """The files written under `root`."""
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    return root
