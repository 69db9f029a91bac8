"""The dataset writer: sequences of simulated scans in the SemanticKITTI layout, or a profile's.

Each sequence gets its own street, along which the sensor drives one scan period per scan.
`simulate_dataset` writes the tree, reproducible byte for byte from its seed; with a dataset
profile, in that profile's layout, point record and raw label ids.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Mapping

import numpy as np

from rangeret.dataset.beams import beam_values
from rangeret.dataset.labels import SEMANTIC_MASK
from rangeret.dataset.layout import labels_dir, velodyne_dir
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.projection import BEAM_ROWS
from rangeret.io.atomic import atomic_write_bytes
from rangeret.io.scans import write_labels, write_scan
from rangeret.sim.classes import raw_label_map
from rangeret.sim.raycast import SensorConfig, SimulationError, simulate_scan
from rangeret.sim.street import make_scene

#: Seconds between two scans (the HDL-64E spins at 10 Hz).
SCAN_PERIOD = 0.1


def _sequence_seed(seed: int, name: str) -> np.random.SeedSequence:
    """The seed of one sequence: the dataset seed and the sequence's name."""
    return np.random.SeedSequence(seed, spawn_key=tuple(name.encode("utf-8")))


def _matrix_line(values: Iterable[float]) -> str:
    """One row-major matrix as a line of the KITTI text files (poses, calibration)."""
    return " ".join(f"{v:.12e}" for v in values)


def sequence_scans(
    name: str,
    count: int,
    sensor: SensorConfig,
    seed: int,
    *,
    profile: DatasetProfile,
    period: float = SCAN_PERIOD,
) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
    """The `count` scans of one simulated sequence, `period` seconds apart along its own street:
    each as (points in the profile's record, uint32 labels as the profile's raw ids with the
    instance in the high 16 bits, the sensor's x along the street). Reproducible from `seed` and
    `name`; every dataset writer draws its scans from here."""
    label_map = raw_label_map(profile)
    seeds = _sequence_seed(seed, name).spawn(count + 1)
    length = max(200.0, 1.25 * count * (period / SCAN_PERIOD))
    scene = make_scene(np.random.default_rng(seeds[0]), length)
    step = scene.ego_speed * period
    for k in range(count):
        points, labels, lasers = simulate_scan(
            scene, k * step, sensor, np.random.default_rng(seeds[k + 1]), lasers=True
        )
        if profile.points.num_fields == 5:
            points = np.column_stack([points, beam_values(lasers, profile)])
        raw = label_map[labels & SEMANTIC_MASK] | (labels & ~np.uint32(SEMANTIC_MASK))
        yield points, raw, k * step


def check_profile(profile: DatasetProfile, sensor: SensorConfig) -> None:
    """ValueError when the simulator cannot fill the profile's point record with this sensor."""
    fields = profile.points.fields
    if fields[4:] not in ((), ("laser_id",), ("ring",)):
        raise SimulationError(
            f"profile {profile.name}: the simulator fills x, y, z, the reflectance and laser_id "
            f"or ring, not the point field {fields[4]!r}"
        )
    height = profile.projection.height
    if profile.projection.row in BEAM_ROWS and sensor.beams > height:
        raise SimulationError(
            f"profile {profile.name} takes rows from beam numbers 0..{height - 1}, "
            f"but the sensor has {sensor.beams} beams"
        )


def simulate_dataset(
    root: str | os.PathLike[str],
    sequences: Mapping[str, int],
    labelled: Iterable[str] | bool = True,
    sensor: SensorConfig | None = None,
    seed: int = 0,
    progress: bool = False,
    *,
    profile: DatasetProfile,
) -> int:
    """Write a simulated dataset tree under `root` and return the number of scans written.

    `sequences` maps a sequence name to its number of scans. Each sequence gets its own street
    and writes `sequences/XX/velodyne/NNNNNN.bin`, `labels/NNNNNN.label` when it is labelled
    (`labelled`: True for all, False for none, or the names of the labelled ones), and
    `poses.txt`, `times.txt` and `calib.txt` (the LiDAR is the reference frame: `Tr` is the
    identity and the poses are the sensor's, its `offset` from the default mounting included).
    The same seed writes the same bytes.

    The sequence folders, ids, point records and raw label ids are the profile's (a laser id,
    where its record has one, is the beam index), and the sensor defaults to
    `SensorConfig.for_profile(profile)`.
    """
    sensor = sensor or SensorConfig.for_profile(profile)
    check_profile(profile, sensor)
    layout, record = profile.layout.folders, profile.points
    if layout is None:
        raise SimulationError(
            f"profile {profile.name} reads a version's tables: simulate it with "
            "rangeret.sim.nuscenes_tree"
        )
    counts = {layout.normalise(name): int(n) for name, n in sequences.items()}
    if any(n < 0 for n in counts.values()):
        raise SimulationError(f"numbers of scans must be >= 0, got {counts}")
    if isinstance(labelled, bool):
        with_labels = set(counts) if labelled else set()
    else:
        with_labels = {layout.normalise(name) for name in labelled}
        unknown = sorted(with_labels - set(counts))
        if unknown:
            raise SimulationError(f"labelled sequences {unknown} are not among the sequences")

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(counts.values()), unit="scan", desc="simulating")
    written = 0
    try:
        for name, n in counts.items():
            seq_dir = velodyne_dir(root, name, layout=layout).parent
            seq_dir.mkdir(parents=True, exist_ok=True)
            poses, times = [], []
            dx, dy, dz = sensor.offset
            scans = sequence_scans(name, n, sensor, seed, profile=profile)
            for k, (points, raw, x) in enumerate(scans):
                write_scan(
                    velodyne_dir(root, name, layout=layout) / f"{k:06d}.bin", points, record=record
                )
                if name in with_labels:
                    write_labels(labels_dir(root, name, layout=layout) / f"{k:06d}.label", raw)
                poses.append(_matrix_line([1, 0, 0, x + dx, 0, 1, 0, dy, 0, 0, 1, dz]))
                times.append(f"{k * SCAN_PERIOD:.6e}")
                written += 1
                if bar is not None:
                    bar.update(1)
            identity = _matrix_line([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0])
            calib = [f"P{i}: {identity}" for i in range(4)] + [f"Tr: {identity}"]
            for file, lines in (("poses.txt", poses), ("times.txt", times), ("calib.txt", calib)):
                atomic_write_bytes(seq_dir / file, "".join(f"{x}\n" for x in lines).encode())
    finally:
        if bar is not None:
            bar.close()
    return written
