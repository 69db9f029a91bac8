"""`--max-loaded` bounds the networks a gateway holds: `rangeret serve`'s own start-up (the
loader, the pool, the check of every model) builds only the networks the pool keeps, an evicted
network is freed, and the networks alive in the process are exactly those the pool says are
loaded, each labelling as it does alone."""

from __future__ import annotations

import asyncio
import gc
import hashlib
import weakref
from pathlib import Path

import numpy as np
import pytest
import torch

from rangeret.dataset.profiles import load_profile
from rangeret.inference.loaded_weights import WeightsChanged
from rangeret.inference.model_set import ModelSet
from rangeret.inference.predictor import Predictor
from rangeret.inference.spec import InferenceSpec
from rangeret.models import RangeRet, build_model, save_checkpoint
from service.labelling.pooled import PooledLabeller
from service.models.loader import ModelLoader
from service.server import build_pool, check_models
from service.settings import Settings

NAMES = ("one", "two", "three")


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Three small checkpoints of their own random weights."""
    folder = tmp_path_factory.mktemp("memory")
    profile = load_profile("semantickitti")
    paths = {}
    for seed, name in enumerate(NAMES):
        torch.manual_seed(seed)
        network = build_model("rangeret-cir", 16, 128, profile.num_classes, layers=1)
        paths[name] = folder / f"{name}.pt"
        save_checkpoint(paths[name], network, profile=profile.to_dict())
    return paths


def _models(checkpoints: dict[str, Path]) -> ModelSet:
    specs = {
        name: InferenceSpec(checkpoint=str(path), device="cpu")
        for name, path in checkpoints.items()
    }
    return ModelSet(specs, "two")


def _held(checkpoints: dict[str, Path]) -> list[str]:
    """The models whose networks are alive in this process, by their checkpoint, after a gc."""
    gc.collect()
    names = {str(path): name for name, path in checkpoints.items()}
    alive = [o for o in gc.get_objects() if issubclass(type(o), RangeRet)]
    return sorted(names[n.checkpoint_info.path] for n in alive if n.checkpoint_info.path in names)


def _start(checkpoints: dict[str, Path], max_loaded: int):
    models = _models(checkpoints)
    loader = ModelLoader(models, batch_size=2, max_wait=0.0)
    pool = build_pool(Settings(max_loaded=max_loaded), loader)
    return pool, check_models(loader, pool)


def test_an_evicted_network_is_freed_and_the_pool_counts_what_the_process_holds(checkpoints):
    points = np.random.default_rng(0).normal(0, 10, (2000, 4)).astype(np.float32)
    alone = {  # at the served precision, the default fp32
        name: Predictor.from_checkpoint(path, device="cpu", precision="fp32").predict(points).labels
        for name, path in checkpoints.items()
    }
    assert _held(checkpoints) == []  # the references are gone with their predictors

    pool, catalog = _start(checkpoints, max_loaded=1)
    assert pool.loaded() == ["two"] and _held(checkpoints) == ["two"]  # the others not built
    assert [(e.name, e.checkpoint_sha256, e.network) for e in catalog] == [
        (name, hashlib.sha256(path.read_bytes()).hexdigest(), "rangeret-cir")
        for name, path in checkpoints.items()
    ]
    labeller = PooledLabeller(pool)

    async def switch_through(order: list[str]) -> None:
        await labeller.start()
        for name in order:
            ((before, runtime),) = pool.items()
            evicted = weakref.ref(runtime.predictor.network)
            del runtime
            labelled = await labeller.label_points(points, model=name)
            assert np.array_equal(labelled.labels, alone[name]), name
            assert pool.loaded() == [name] and _held(checkpoints) == [name], name
            assert (evicted() is None) == (before != name), (before, name)
        await labeller.stop()

    asyncio.run(switch_through(["one", "three", "three", "two", "one"]))
    assert pool.loads == {"one": 2, "two": 2, "three": 1}


def test_a_pool_with_room_for_every_model_holds_each_network_once(checkpoints):
    pool, _ = _start(checkpoints, max_loaded=3)
    assert pool.loaded() == ["two", "one", "three"]  # the default first
    assert _held(checkpoints) == sorted(NAMES)
    with pool.use("one"):
        pass
    assert _held(checkpoints) == sorted(NAMES) and pool.loads == dict.fromkeys(NAMES, 1)


def test_a_checkpoint_changed_since_the_start_is_refused_when_loaded_again(checkpoints, tmp_path):
    changed = dict(checkpoints, three=tmp_path / "three.pt")
    changed["three"].write_bytes(checkpoints["three"].read_bytes())
    pool, _ = _start(changed, max_loaded=1)
    torch.manual_seed(9)
    network = build_model("rangeret-cir", 16, 128, 20, layers=1)
    save_checkpoint(changed["three"], network, profile=load_profile("semantickitti").to_dict())
    with pytest.raises(
        WeightsChanged,
        match=r"model three: .* of sha256 \w+, not the checkpoint of sha256 \w+ read when the gateway",
    ):
        pool.acquire("three")
    assert pool.loaded() == [] and pool.held() == []
