"""What a speed card times (`rangeret.inference.speed_card`): the network, from a checkpoint, a
published model or random weights of a named network, and the scan, simulated or read from a file.

Speed depends on the network's shape, not on its weights, so random weights of a published
model's network time it as well as its own; only the labels' agreement between precisions
depends on the weights.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.exceptions import InputError
from rangeret.inference.loaded_weights import LoadedWeights, load_weights
from rangeret.inference.spec import InferenceSpec

#: The published model a card times by default (its own weights once downloaded).
DEFAULT_MODEL = "rangeret-kitti-657"


class BenchError(InputError, ValueError):
    """A speed card that cannot be made as asked: one sentence saying why."""


@dataclass(frozen=True)
class BenchWeights:
    """The network a card times: the loaded weights, the network's name, where the weights came
    from (`source`: a checkpoint's path, or `random`) and a note saying why they are random."""

    weights: LoadedWeights
    model: str
    source: str
    note: str | None = None


def bench_weights(
    checkpoint: str | None = None,
    *,
    model: str | None = None,
    profile: str | None = None,
    height: int | None = None,
    width: int | None = None,
    random: bool = False,
    seed: int = 0,
) -> BenchWeights:
    """The network to time, at its profile's resolution unless `height` or `width` are given.

    `checkpoint` is a file or a published model's name; without one, `model` names a network to
    time with random weights, else `DEFAULT_MODEL` is timed. `random` times random weights of the
    checkpoint's network. A published model named on the command line is fetched when it is not
    in the cache, and stands in as random weights of its network when it cannot be fetched; the
    default one is never fetched (random weights of its network until `rangeret weights
    download` has put it in the cache). Speed depends on the network, not on its weights; the
    labels' agreement does."""
    from rangeret.models.weights.hub import WeightsError, cached_weights, published_name

    if checkpoint is None and model is not None:
        return _random(model, _profile(profile, height, width), {}, seed, "no checkpoint given")
    name = checkpoint or DEFAULT_MODEL
    published = published_name(name)
    if published is not None:
        shape = _profile(profile or published.profile, height, width, published)
        network = (model or published.model, shape, {"layers": published.blocks}, seed)
        if random:
            return _random(*network, "--random")
        if checkpoint is None and cached_weights(published) is None:
            return _random(
                *network, f"{name} is not downloaded; rangeret weights download {name} to time it"
            )
        try:
            loaded = load_weights(_spec(name, model, profile, height, width))
        except WeightsError as exc:
            return _random(*network, str(exc))
        return BenchWeights(loaded, network[0], str(loaded.info.path) if loaded.info else name)
    if not Path(name).is_file():
        raise BenchError(f"--checkpoint {name}: no such file, nor a published model's name")
    loaded = load_weights(_spec(name, model, profile, height, width))
    if not random:
        return BenchWeights(loaded, loaded.model, name)
    from rangeret.models.network import RangeRet

    torch.manual_seed(seed)
    fresh = RangeRet(loaded.network.config).eval()
    return BenchWeights(LoadedWeights(fresh, loaded.profile), loaded.model, "random", "--random")


def _spec(
    checkpoint: str, model: str | None, profile: str | None, height: int | None, width: int | None
) -> InferenceSpec:
    return InferenceSpec(
        checkpoint=checkpoint, model=model, profile=profile, height=height, width=width
    )


def _profile(
    name: str | None, height: int | None, width: int | None, published: Any = None
) -> DatasetProfile:
    """The profile `name` (default semantickitti) at `height` x `width`, else at the published
    model's resolution, else at its own."""
    profile = load_profile(name or "semantickitti")
    if published is not None:
        height = height or published.height or None
        width = width or published.width or None
    return profile.with_overrides(height=height, width=width)


def _random(
    model: str, profile: DatasetProfile, overrides: dict[str, Any], seed: int, why: str
) -> BenchWeights:
    """Random weights of `model` (with `overrides`) at `profile`'s resolution, from `seed`,
    saying `why` they are random."""
    from rangeret.models import build_model

    torch.manual_seed(seed)
    p = profile.projection
    network = build_model(model, p.height, p.width, profile.num_classes, **overrides)
    return BenchWeights(LoadedWeights.of_network(network, profile), model, "random", why)


# The scan ---------------------------------------------------------------------------------------


def simulated_scan(profile: DatasetProfile, seed: int = 0) -> np.ndarray:
    """One scan of a simulated street by the profile's sensor, in its point record."""
    from rangeret.sim import SensorConfig
    from rangeret.sim.dataset import check_profile, sequence_scans

    sensor = SensorConfig.for_profile(profile)
    try:
        check_profile(profile, sensor)
    except ValueError as exc:
        raise BenchError(f"cannot simulate a {profile.name} scan ({exc}): pass --scan") from exc
    points, _, _ = next(sequence_scans("bench", 1, sensor, seed, profile=profile))
    return np.ascontiguousarray(points, dtype=np.float32)


def read_bench_scan(path: str | Path, profile: DatasetProfile) -> np.ndarray:
    """The scan file `path` in the profile's point record."""
    from rangeret.io.scans import read_scan

    return read_scan(path, profile.points)
