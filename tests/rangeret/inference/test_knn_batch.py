"""kNN refinement of batches (`rangeret.inference.knn.refine_batch`): each scan's `refine` result
bit for bit, whatever the batch, its sizes and the rule's parameters; a fixed number of waits on
the host whatever the batch size; host arrays to the device in one copy, pinned on CUDA."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rangeret.inference.knn import refine_batch, to_device
from rangeret.inference.settings import DEFAULT_KNN, KnnSettings
from rangeret.knn import refine
from tests.rangeret.inference.test_knn import FIXTURE, INPUTS, inputs, random_scan
from tests.support.host_syncs import SYNCS_PER_BATCH, host_syncs
from tests.support.paths import data_path


@pytest.fixture(scope="module")
def scan() -> dict[str, np.ndarray]:
    """The real scan's test vector: its arrays."""
    with np.load(data_path(FIXTURE)) as data:
        return {name: data[name] for name in data.files}


def random_batch(seed: int, sizes: list[int], **kwargs) -> list[dict[str, np.ndarray]]:
    """Random scans of one image size with `sizes` points each."""
    return [random_scan(seed + i, points=n, **kwargs) for i, n in enumerate(sizes)]


def batch_refined(
    scans: list[dict[str, np.ndarray]],
    knn: KnnSettings = DEFAULT_KNN,
    num_classes: int = 20,
    device: str = "cpu",
    **kwargs,
) -> torch.Tensor:
    """`refine_batch` as `Predictor` calls it: the argmax a (B, H, W) tensor on the device, each
    scan's projection arrays as numpy arrays."""
    argmax = torch.from_numpy(np.stack([s["proj_argmax"] for s in scans])).to(device)
    parts = [
        [s[name] for s in scans] for name in ("proj_range", "unproj_range", "proj_x", "proj_y")
    ]
    return refine_batch(argmax, *parts, knn, num_classes, **kwargs)


def per_scan(scans, *args, **kwargs) -> np.ndarray:
    """`refine` scan by scan, concatenated."""
    return np.concatenate([refine(*inputs(scan), *args, **kwargs) for scan in scans])


@pytest.mark.parametrize("votes_from", [0, 1])
@pytest.mark.parametrize(
    ("k", "search", "cutoff"), [(7, 7, 1.0), (5, 5, 1.0), (3, 3, 0.0), (9, 3, 1.0), (1, 1, 1.0)]
)
def test_a_batch_gives_each_scans_result(votes_from, k, search, cutoff):
    scans = random_batch(10, [300, 1, 0, 57, 410])
    rule = {"votes_from": votes_from, "unprojected": 4}
    expected = per_scan(scans, k, search, 1.0, cutoff, 5, **rule)
    knn = KnnSettings(k, search, 1.0, cutoff)
    for chunk_size in (37, 300, None):
        result = batch_refined(scans, knn, 5, chunk_size=chunk_size, **rule)
        assert isinstance(result, torch.Tensor) and result.dtype == torch.int64
        assert np.array_equal(result.numpy(), expected), chunk_size


@pytest.mark.parametrize("votes_from", [0, 1])
def test_a_batch_with_the_real_scan_gives_each_scans_result(scan, votes_from):
    real = {name: scan[name] for name in INPUTS}
    dropped = dict(real, proj_x=real["proj_x"].copy(), proj_y=real["proj_y"].copy())
    dropped["proj_x"][::50] = dropped["proj_y"][::50] = -1
    scans = [real, random_scan(3, 64, 1024, 20_000, 20), dropped]
    rule = {"votes_from": votes_from, "unprojected": 19}
    result = batch_refined(scans, chunk_size=50_000, **rule).numpy()
    assert np.array_equal(result, per_scan(scans, **rule))
    if votes_from == 1:
        assert np.array_equal(result[: len(real["proj_x"])], scan["expected_knn7_search7"])


@pytest.mark.parametrize("kind", ["numpy", "tensor"])
def test_bad_values_are_named(kind):
    """Numpy arrays and tensors alike, before any work."""
    data = random_batch(40, [300, 200])[1]
    args = inputs(data)
    convert = np.asarray if kind == "numpy" else torch.from_numpy
    cases = [
        (2, args[2] + 20, "proj_argmax", r"\[0, 20\)"),
        (2, args[2] - 3, "proj_argmax", r"\[-3,"),
        (3, np.where(args[3] == 0, 20, args[3]), "proj_x", "width 20"),
        (3, args[3] - 2, "proj_x", "-1"),
        (4, np.where(args[3] >= 0, args[4] + 6, -1), "proj_y", r"11\]"),
    ]
    for position, value, name, detail in cases:
        broken = [convert(part) for part in args]
        broken[position] = convert(value)
        with pytest.raises(ValueError, match=name) as raised:
            refine(*broken)
        assert raised.match(detail)


@pytest.mark.parametrize("scans", [1, 5])
def test_a_batch_waits_on_the_host_a_fixed_number_of_times(scans):
    """As `Predictor` calls it: projections as numpy arrays, the argmax a tensor on the device.

    On CUDA each counted call is a wait for the device; the count is the same for 1 or 5 scans
    and with chunks of 37 points (tens of chunks).
    """
    batch = random_batch(50, [300, 120, 0, 411, 77][:scans])
    expected = per_scan(batch)
    with host_syncs() as counts:
        result = batch_refined(batch, chunk_size=37).cpu()
    assert counts == {"cpu": 1}
    assert sum(counts.values()) == SYNCS_PER_BATCH
    assert np.array_equal(result.numpy(), expected)


def test_to_device_concatenates_and_converts():
    parts = [np.arange(6, dtype=np.int32).reshape(2, 3), np.full((1, 3), 7, dtype=np.uint8)]
    moved = to_device(parts, torch.int64, torch.device("cpu"), pinned=False)
    assert moved.dtype == torch.int64
    assert moved.tolist() == [[0, 1, 2], [3, 4, 5], [7, 7, 7]]


def test_to_device_pins_and_does_not_block_when_asked(monkeypatch):
    """The CUDA branch, run on the CPU: page-locked staging, copy with non_blocking."""
    asked = []
    empty, to = torch.empty, torch.Tensor.to

    def recording_empty(*args, pin_memory=False, **kwargs):
        asked.append(("pin_memory", pin_memory))
        return empty(*args, **kwargs)

    def recording_to(self, *args, non_blocking=False, **kwargs):
        asked.append(("non_blocking", non_blocking))
        return to(self, *args, non_blocking=non_blocking, **kwargs)

    monkeypatch.setattr(torch, "empty", recording_empty)
    monkeypatch.setattr(torch.Tensor, "to", recording_to)
    parts = [np.array([0.5, 1.5]), np.array([2.5], dtype=np.float32)]
    moved = to_device(parts, torch.float32, torch.device("cpu"), pinned=True)
    assert moved.tolist() == [0.5, 1.5, 2.5]
    assert asked == [("pin_memory", True), ("non_blocking", True)]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_batch_matches_cpu_and_waits_a_fixed_number_of_times():
    with np.load(data_path(FIXTURE)) as fixture:
        real = {name: fixture[name] for name in INPUTS}
    batch = [real, random_scan(3, 64, 1024, 20_000, 20), real]
    expected = batch_refined(batch, chunk_size=40_000)
    with host_syncs() as counts:
        result = batch_refined(batch, device="cuda", chunk_size=40_000).cpu()
    assert sum(counts.values()) <= SYNCS_PER_BATCH
    assert np.array_equal(result.numpy(), expected.numpy())
