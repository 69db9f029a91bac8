"""The gateway's pool of loaded networks: at most N loaded, least recently used out unless held,
one load per model however many ask at once, `PoolFull` when every slot is held, and real
networks that label as they would alone."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch

from rangeret.dataset.profiles import load_profile
from rangeret.inference.predictor import Predictor
from rangeret.models import build_model, save_checkpoint
from service.models.pool import ModelPool, PoolFull


class Loads:
    """A loader that records what it built and what was unloaded."""

    def __init__(self, delay: float = 0.0) -> None:
        self.built: list[str] = []
        self.unloaded: list[str] = []
        self.delay = delay

    def load(self, name: str) -> dict[str, str]:
        time.sleep(self.delay)
        self.built.append(name)
        return {"name": name}

    def unload(self, item: dict[str, str]) -> None:
        self.unloaded.append(item["name"])


def test_the_least_recently_used_unheld_model_goes_first():
    loads = Loads()
    pool = ModelPool(["a", "b", "c"], loads.load, max_loaded=2, unload=loads.unload)
    for name in ("a", "b", "a", "c"):
        with pool.use(name) as item:
            assert item == {"name": name}
    assert loads.built == ["a", "b", "c"] and loads.unloaded == ["b"]
    assert pool.loaded() == ["a", "c"]
    with pool.use("b"):
        pass
    assert loads.unloaded == ["b", "a"] and pool.loads == {"a": 1, "b": 2, "c": 1}


def test_a_held_model_is_never_evicted_and_a_full_pool_says_so():
    loads = Loads()
    pool = ModelPool(["a", "b"], loads.load, max_loaded=1, unload=loads.unload)
    with pool.use("a"):
        with (
            pytest.raises(
                PoolFull, match=r"the model b is not loaded and every loaded one is in use \(a\)"
            ),
            pool.use("b"),
        ):
            pass
        assert pool.loaded() == ["a"] and pool.held() == ["a"]
    with pool.use("b"):
        assert pool.loaded() == ["b"]
    assert pool.held() == [] and loads.unloaded == ["a"]


def test_every_model_loads_once_however_many_ask_at_once():
    loads = Loads(delay=0.2)
    pool = ModelPool(["a", "b"], loads.load)
    seen: list[dict[str, str]] = []
    threads = [threading.Thread(target=lambda: seen.append(_use(pool, "a"))) for _ in range(6)]
    started = time.perf_counter()
    for t in threads:
        t.start()
    with pool.use("b"):
        pass  # a loaded model's request does not wait behind another model's load
    assert time.perf_counter() - started < 0.4 + 0.2
    for t in threads:
        t.join()
    assert loads.built.count("a") == 1 and len(seen) == 6 and all(s is seen[0] for s in seen)


def _use(pool: ModelPool, name: str) -> dict[str, str]:
    with pool.use(name) as item:
        return item


def test_a_failed_load_holds_nothing_and_the_next_use_tries_again():
    calls = []

    def load(name: str) -> str:
        calls.append(name)
        if len(calls) == 1:
            raise OSError("the disk went away")
        return name

    pool = ModelPool(["a"], load, max_loaded=1)
    with pytest.raises(OSError), pool.use("a"):
        pass
    assert pool.held() == [] and pool.loaded() == []
    with pool.use("a") as item:
        assert item == "a"
    assert calls == ["a", "a"] and pool.loads == {"a": 1}


def test_real_networks_alternating_through_one_slot_label_as_alone(tmp_path):
    profile = load_profile("semantickitti")
    paths = {}
    for name, seed in (("one", 0), ("two", 1)):
        torch.manual_seed(seed)
        network = build_model("rangeret-cir", 16, 128, profile.num_classes, layers=1)
        paths[name] = tmp_path / f"{name}.pt"
        save_checkpoint(paths[name], network, profile=profile.to_dict())
    alone = {name: Predictor.from_checkpoint(path, device="cpu") for name, path in paths.items()}
    pool = ModelPool(
        list(paths), lambda name: Predictor.from_checkpoint(paths[name], device="cpu"), max_loaded=1
    )
    points = np.random.default_rng(0).normal(0, 10, (2000, 4)).astype(np.float32)
    answers = {name: alone[name].predict(points).labels for name in paths}
    assert not np.array_equal(answers["one"], answers["two"])
    for name in ("one", "two", "one", "two"):
        with pool.use(name) as predictor:
            assert np.array_equal(predictor.predict(points).labels, answers[name]), name
        assert pool.loaded() == [name]
    assert pool.loads == {"one": 2, "two": 2}
