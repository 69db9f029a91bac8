"""The CPU's fast path of kNN refinement (`rangeret.inference.knn_cpu`: int16 keys from scaled
distances) must give the exact rule's labels wherever it settles a point: on scans made of ties,
distances on its bucket edges and at the cutoff, one or two voters, crowded pixels, ranges that
are not numbers, any thread count, and in and out of `torch.inference_mode` in one process."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rangeret.inference import knn_cpu, knn_rule
from rangeret.inference.knn import gaussian_kernel
from rangeret.inference.settings import KnnSettings
from rangeret.knn import refine
from tests.rangeret.inference.test_knn import (
    FIXTURE,
    inputs,
    random_scan,
    reference,
    scan_arrays,
)
from tests.rangeret.inference.test_knn_batch import batch_refined
from tests.support.paths import data_path


@pytest.fixture(scope="module")
def real() -> dict[str, np.ndarray]:
    """The real scan's test vector: its arrays."""
    with np.load(data_path(FIXTURE)) as data:
        return {name: data[name] for name in data.files}


def plain_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """Turn the CPU's fast path off: every point goes through the exact rule."""
    monkeypatch.setattr(knn_cpu._Quantized, "applies", staticmethod(lambda *args: False))


def counting_open_points(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The number of points each call of the exact rule's window gets, as a list that grows."""
    counts: list[int] = []
    window = knn_cpu._Padded.window

    def counted(self, columns, *args):
        counts.append(len(columns))
        return window(self, columns, *args)

    monkeypatch.setattr(knn_cpu._Padded, "window", counted)
    return counts


def tie_heavy_scan(seed: int, step: float, num_classes: int) -> dict[str, np.ndarray]:
    """A 16 x 64 scan of 3000 points on ranges `step` apart: many distances are equal or fall
    in one bucket of the fast path; a quarter of the pixels are empty."""
    rng = np.random.default_rng(seed)
    height, width, points = 16, 64, 3000
    image = (rng.integers(1, 40, (height, width)) * step + 2.0).astype(np.float32)
    image[rng.random((height, width)) < 0.25] = -1
    proj_y = rng.integers(0, height, points)
    proj_x = rng.integers(0, width, points)
    near = image[proj_y, proj_x] + rng.integers(-3, 4, points) * step
    own = np.where(image[proj_y, proj_x] < 0, np.float32(2.0), near).astype(np.float32)
    proj_x[rng.random(points) < 0.02] = -1
    return scan_arrays(image, own, rng.integers(0, num_classes, (height, width)), proj_x, proj_y)


@pytest.mark.parametrize("votes_from", [0, 1])
@pytest.mark.parametrize(
    ("k", "search", "cutoff", "step", "num_classes"),
    [
        (7, 7, 1.0, 0.25, 20),
        (7, 7, 1.0, 1 / 1024, 20),
        (5, 5, 0.5, 1 / 2048, 20),
        (3, 3, 2.0, 0.01, 5),
        (12, 7, 0.7, 0.003, 31),
        (9, 3, 1.0, 1 / 512, 60),
        (49, 7, 1.0, 0.05, 20),
    ],
)
def test_the_fast_path_gives_the_plain_paths_labels(
    monkeypatch, votes_from, k, search, cutoff, step, num_classes
):
    scans = [tie_heavy_scan(seed, step, num_classes) for seed in range(3)]
    knn = KnnSettings(k, search, 1.0, cutoff)
    rule = {"votes_from": votes_from, "unprojected": num_classes - 1}
    with monkeypatch.context() as patch:
        opened = counting_open_points(patch)
        fast = batch_refined(scans, knn, num_classes, chunk_size=700, **rule)
    # points left to the exact rule: some (ties at the k-th place), not most
    assert sum(opened) < 0.9 * sum(len(s["proj_x"]) for s in scans)
    assert sum(opened) > 0 or k == search * search
    plain_path(monkeypatch)
    assert torch.equal(fast, batch_refined(scans, knn, num_classes, **rule))


def test_distances_on_the_cutoff_and_next_to_it():
    # search 3, sigma 1: an edge neighbour's weight is w = 1 - 0.1238; ranges chosen so that
    # |dr| * w lands on the cutoff itself, one float below and one float above it.
    w = np.float32(1.0) - gaussian_kernel(3, 1.0)[0, 1].numpy()
    rows = []
    for distance in (np.float32(1.0), np.nextafter(np.float32(1.0), 0), np.float32(1.0000001)):
        dr = np.float32(distance / w)
        while np.float32(dr * w) > distance:
            dr = np.nextafter(dr, np.float32(0))
        while np.float32(dr * w) < distance:
            dr = np.nextafter(dr, np.float32(np.inf))
        rows.append(dr)
    image = np.full((3, 3 * len(rows)), 50.0, dtype=np.float32)
    classes = np.ones(image.shape, dtype=np.int64)
    for i, dr in enumerate(rows):
        image[1, 3 * i] = np.float32(10.0) + dr  # left edge neighbour of the centre below
        image[1, 3 * i + 1] = 10.0
        classes[1, 3 * i] = 3
    data = {
        "proj_range": image,
        "unproj_range": np.full(len(rows), 10.0, dtype=np.float32),
        "proj_argmax": classes,
        "proj_x": np.arange(len(rows)) * 3 + 1,
        "proj_y": np.ones(len(rows), dtype=np.int64),
    }
    expected = reference(data, 3, 3, 1.0, 1.0, 5)
    assert refine(*inputs(data), k=3, search=3, num_classes=5).tolist() == expected.tolist()


@pytest.mark.parametrize(("k", "search"), [(1, 5), (2, 3), (7, 7)])
@pytest.mark.parametrize("everywhere", [True, False])
def test_the_fast_path_with_one_or_two_voters_and_crowded_pixels(
    monkeypatch, k, search, everywhere
):
    # one or two voters; every point projected or not; pixels holding up to a dozen points,
    # some of them with the pixel's own range, so that layers overlap and most are gathered
    scans = [tie_heavy_scan(seed, 0.25, 20) for seed in range(2)]
    for scan in scans:
        scan["proj_y"][:600] = 3
        scan["proj_x"][:600] = np.arange(600) % 50
        pixel = scan["proj_range"][3, np.arange(600) % 50]
        scan["unproj_range"][:300] = np.where(pixel[:300] > 0, pixel[:300], 2.0)
        if everywhere:
            scan["proj_y"][scan["proj_x"] < 0] = 0
            scan["proj_x"][scan["proj_x"] < 0] = 0
    knn = KnnSettings(k, search, 1.0, 1.0)
    fast = batch_refined(scans, knn, 20, chunk_size=500)
    plain_path(monkeypatch)
    assert torch.equal(fast, batch_refined(scans, knn, 20))


def test_the_network_gives_the_smallest_in_order():
    rng = np.random.default_rng(3)
    values = torch.from_numpy(rng.integers(-5, 5, (9, 40)).astype(np.int16))
    for count in (1, 3, 8, 10):
        got = knn_rule.smallest(values, count, 99, skip=4)
        rest = torch.cat([values[:4], values[5:], torch.full((max(0, count - 8), 40), 99)])
        expected = rest.to(torch.int16).sort(0).values[:count]
        assert torch.equal(got, expected), count


@pytest.mark.parametrize("broken", ["nan pixel", "infinite point"])
def test_ranges_that_are_not_numbers_take_the_plain_path(monkeypatch, broken):
    data = random_scan(7, 12, 40, 800, 5)
    if broken == "nan pixel":
        data["proj_range"][3, 5] = np.nan
    else:
        data["unproj_range"][int(np.flatnonzero(data["proj_x"] >= 0)[0])] = np.inf
    knn = KnnSettings(5, 5, 1.0, 1.0)
    result = batch_refined([data], knn, 5)
    plain_path(monkeypatch)
    assert torch.equal(result, batch_refined([data], knn, 5))


def test_threads_give_the_same_labels_and_are_restored(real):
    published = real["expected_knn7_search7"]
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        two = refine(*inputs(real))
        assert torch.get_num_threads() == 2
        torch.set_num_threads(1)
        one = refine(*inputs(real))
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
    assert np.array_equal(two, published) and np.array_equal(one, published)


def test_refinement_runs_in_and_out_of_inference_mode_in_one_thread(real):
    """Buffers kept between calls are made per inference mode: one made under
    `torch.inference_mode` (a validation pass in training) cannot be written outside it (a later
    `predict` in the same process), which failed every scan before."""
    published = real["expected_knn7_search7"]
    with torch.inference_mode():
        inside = refine(*inputs(real))
    with torch.no_grad():
        outside = refine(*inputs(real))
    with torch.inference_mode():
        again = refine(*inputs(real))
    for labels in (inside, outside, again):
        assert np.array_equal(labels, published)
