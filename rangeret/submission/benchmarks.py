"""The benchmark registry: every `Benchmark` by name, the built-ins and those of other packages.

A profile names its benchmark in `benchmark.name` (`rangeret profile show` prints it);
`benchmark_of(profile)` gives the entry every runner asks for the archive, the job zip and the
demo's plan, or the base `Benchmark` (no archive) for a profile that names none. Built in:
`semantickitti` (`rangeret.submission.kitti_benchmark`) and `nuscenes-lidarseg`
(`rangeret.submission.nuscenes_benchmark`). Another package adds one through the entry-point
group `rangeret.benchmarks`, whose object is a `Benchmark` instance (docs/benchmarks.md); an
entry that fails to load, or takes a built-in's name, is logged and left out.
"""

from __future__ import annotations

import logging
from functools import cache

from rangeret.dataset.profiles import DatasetProfile, ProfileError
from rangeret.plugins import load_plugins
from rangeret.submission.benchmark import Benchmark
from rangeret.submission.kitti_benchmark import SEMANTICKITTI
from rangeret.submission.kitti_panoptic_benchmark import SEMANTICKITTI_PANOPTIC
from rangeret.submission.nuscenes_benchmark import NUSCENES_LIDARSEG, NUSCENES_PANOPTIC

log = logging.getLogger(__name__)

BENCHMARKS_GROUP = "rangeret.benchmarks"
BUILTIN_BENCHMARKS: tuple[Benchmark, ...] = (
    SEMANTICKITTI,
    NUSCENES_LIDARSEG,
    SEMANTICKITTI_PANOPTIC,
    NUSCENES_PANOPTIC,
)
#: The entry of a profile that names no benchmark: no archive, the plain job zip and demo.
NO_BENCHMARK = Benchmark()


@cache
def registered() -> dict[str, Benchmark]:
    """Every benchmark by name: the built-ins, then the entry points' in name order."""
    found = {b.name: b for b in BUILTIN_BENCHMARKS}
    for plugin in load_plugins(BENCHMARKS_GROUP):
        if not isinstance(plugin, Benchmark) or not plugin.name:
            log.warning("%s: %r is not a named Benchmark; left out", BENCHMARKS_GROUP, plugin)
        elif plugin.name in found:
            log.warning(
                "%s: a second benchmark named %s is left out", BENCHMARKS_GROUP, plugin.name
            )
        else:
            found[plugin.name] = plugin
    return found


def benchmark_named(name: str) -> Benchmark:
    """The benchmark called `name`; a `ProfileError` naming the known ones otherwise."""
    found = registered().get(name)
    if found is None:
        raise ProfileError(
            f"benchmark.name {name!r} is not a known benchmark; known: {', '.join(registered())}"
        )
    return found


def benchmark_of(profile: DatasetProfile, *, panoptic: bool = False) -> Benchmark:
    """The benchmark the profile names (`benchmark.name`, or with `panoptic` its
    `benchmark.panoptic`; `NO_BENCHMARK` where it names none); a `ProfileError` when it is
    unknown or cannot take the profile's layout."""
    name = profile.benchmark.panoptic if panoptic else profile.benchmark.name
    if name is None:
        return NO_BENCHMARK
    benchmark = benchmark_named(name)
    refusal = benchmark.check_profile(profile)
    if refusal is not None:
        raise ProfileError(f"profile {profile.name}: {refusal}")
    return benchmark


def no_archive_reason(profile: DatasetProfile, *, panoptic: bool = False) -> str | None:
    """Why the profile has no benchmark archive (with `panoptic`, no panoptic one), or None
    where it has one."""
    if benchmark_of(profile, panoptic=panoptic).writes_archives:
        return None
    titles = " and ".join(b.title for b in registered().values() if b.writes_archives)
    task = "panoptic " if panoptic else ""
    return (
        f"submission archives are the {titles} benchmarks' formats; the {profile.name} profile "
        f"has no such {task}archive (use `rangeret evaluate` on its predictions instead)"
    )
