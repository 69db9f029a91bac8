"""The CPU's compiled vote (`rangeret.inference.knn_native`, `csrc/knn_vote.c`) must be built
and give the exact rule's labels in every instruction set this CPU runs: on scans made of ties,
distances at the cutoff and next to it, one or two voters, crowded pixels, with or without a
cutoff, classes that count from 0, any number of threads; it declines what it does not take
(ranges that are not numbers, more voters than it keeps) and refuses pixels outside the image."""

from __future__ import annotations

import importlib.machinery
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from rangeret.inference import knn, knn_native, knn_rule
from rangeret.inference.settings import KnnSettings
from rangeret.knn import refine
from tests.rangeret.inference.test_knn import (
    FIXTURE,
    inputs,
    random_scan,
    reference,
    scan_arrays,
    torch_rule_only,
)
from tests.rangeret.inference.test_knn_batch import batch_refined
from tests.support.paths import data_path

#: Every instruction set this CPU runs the library in.
ISAS = list(range(1, knn_native.best_isa() + 1))


@pytest.fixture(scope="module")
def real() -> dict[str, np.ndarray]:
    """The real scan's test vector: its arrays."""
    with np.load(data_path(FIXTURE)) as data:
        return {name: data[name] for name in data.files}


def voted(
    scan: dict[str, np.ndarray],
    settings: KnnSettings,
    num_classes: int,
    votes_from: int = 1,
    unprojected: int = 0,
    **options,
) -> np.ndarray | None:
    """`vote_on_cpu` on one scan (points without a pixel keep `unprojected`); None where it
    declines."""
    result = np.full(len(scan["unproj_range"]), unprojected, dtype=np.int64)
    done = knn_native.vote_on_cpu(
        result,
        scan["proj_argmax"],
        scan["proj_range"],
        scan["unproj_range"],
        scan["proj_x"],
        scan["proj_y"],
        settings,
        num_classes,
        votes_from,
        **options,
    )
    return result if done else None


def tie_heavy_scan(seed: int, step: float, num_classes: int) -> dict[str, np.ndarray]:
    """A 16 x 64 scan of 3000 points on ranges `step` apart: many distances are equal; a quarter
    of the pixels are empty, 2 % of the points have no pixel."""
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


def test_the_library_is_built_for_this_cpu():
    assert knn_native.built(), "the package was installed without its compiled kNN vote"
    assert knn_native.best_isa() in knn_native.ISA_NAMES
    assert knn_native.slots() == 64


def test_without_the_library_the_torch_rule_labels_and_it_is_said_once(
    monkeypatch, tmp_path, caplog, real
):
    monkeypatch.setattr(knn_native, "_library", lambda: knn_native._load((tmp_path,)))
    with caplog.at_level("WARNING", logger=knn_native.__name__):
        assert not knn_native.built() and knn_native.slots() == 0
        assert voted(real, KnnSettings(7, 7, 1.0, 1.0), 20) is None
        assert np.array_equal(refine(*inputs(real)), real["expected_knn7_search7"])
    said = [r.getMessage() for r in caplog.records if "not built" in r.getMessage()]
    assert said == [
        f"kNN refinement's compiled vote ({tmp_path}/_knn_vote*.so) is not built: the CPU runs "
        "the exact rule in torch, several times slower; reinstall the package where a C compiler "
        "is found"
    ]


@pytest.mark.parametrize("isa", ISAS)
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
        (7, 7, 0.0, 0.25, 20),
        (65, 9, 1.0, 0.05, 300),
    ],
)
def test_every_instruction_set_gives_the_exact_rules_labels(
    monkeypatch, isa, votes_from, k, search, cutoff, step, num_classes
):
    settings = KnnSettings(k, search, 1.0, cutoff)
    rule = {"votes_from": votes_from, "unprojected": num_classes - 1}
    scans = [tie_heavy_scan(seed, step, num_classes) for seed in range(3)]
    compiled = np.concatenate([voted(s, settings, num_classes, isa=isa, **rule) for s in scans])
    torch_rule_only(monkeypatch)
    assert np.array_equal(compiled, batch_refined(scans, settings, num_classes, **rule).numpy())


@pytest.mark.parametrize("isa", ISAS)
def test_distances_on_the_cutoff_and_next_to_it(monkeypatch, isa):
    # search 3, sigma 1: an edge neighbour's weight is w = 1 - 0.1238. Its range one float
    # below, at and one float above 10 + 1 / w, the centre's range 10: the cutoff is the middle
    # one's distance, |difference| exact (Sterbenz) and times w rounded as the published code.
    w = np.float32(1.0) - knn.gaussian_kernel(3, 1.0)[0, 1].numpy()
    on = np.float32(10.0 + 1.0 / w)
    cutoff = np.float32((on - np.float32(10.0)) * w)
    sides = [on, np.nextafter(on, np.float32(0)), np.nextafter(on, np.float32(np.inf))]
    distances = [np.float32((v - np.float32(10.0)) * w) for v in sides]
    assert distances[1] < cutoff == distances[0] < distances[2]
    image = np.full((3, 3 * len(sides)), 50.0, dtype=np.float32)
    classes = np.ones(image.shape, dtype=np.int64)
    for i, value in enumerate(sides):
        image[1, 3 * i] = value  # left edge neighbour of the centre beside it
        image[1, 3 * i + 1] = 10.0
        classes[1, 3 * i] = 3
        classes[1, 3 * i + 1] = 0  # the centre's class does not vote: the neighbour decides
    data = scan_arrays(
        image,
        np.full(len(sides), 10.0, dtype=np.float32),
        classes,
        np.arange(len(sides)) * 3 + 1,
        np.ones(len(sides), dtype=np.int64),
    )
    expected = reference(data, 3, 3, 1.0, float(cutoff), 5)
    assert expected.tolist() == [3, 3, 1]  # on the cutoff and below it vote, above it not
    settings = KnnSettings(3, 3, 1.0, float(cutoff))
    assert voted(data, settings, 5, isa=isa).tolist() == expected.tolist()
    torch_rule_only(monkeypatch)
    assert refine(*inputs(data), k=3, search=3, cutoff=float(cutoff), num_classes=5).tolist() == [
        3,
        3,
        1,
    ]


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize(("k", "search"), [(1, 5), (2, 3), (7, 7)])
def test_one_or_two_voters_and_crowded_pixels(isa, k, search):
    # pixels holding up to a dozen points, some of them with the pixel's own range
    scan = tie_heavy_scan(5, 0.25, 20)
    scan["proj_y"][:600] = 3
    scan["proj_x"][:600] = np.arange(600) % 50
    pixel = scan["proj_range"][3, np.arange(600) % 50]
    scan["unproj_range"][:300] = np.where(pixel[:300] > 0, pixel[:300], 2.0)
    expected = reference(scan, k, search, 1.0, 1.0, 20)
    assert np.array_equal(voted(scan, KnnSettings(k, search, 1.0, 1.0), 20, isa=isa), expected)


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("threads", [1, 2, 3, 7])
def test_threads_and_instruction_sets_give_the_published_labels(real, isa, threads):
    settings = KnnSettings(7, 7, 1.0, 1.0)
    labels = voted(real, settings, 20, threads=threads, isa=isa)
    assert np.array_equal(labels, real["expected_knn7_search7"])


def test_a_forked_child_votes_on_threads_of_its_own(real):
    """A child forked after a vote (a data loader's worker, a forking server) has none of the
    parent's pool threads: it makes its own instead of waiting on threads that do not exist."""
    settings = KnnSettings(7, 7, 1.0, 1.0)
    assert np.array_equal(voted(real, settings, 20, threads=2), real["expected_knn7_search7"])
    child = os.fork()
    if child == 0:  # pragma: no cover - the child reports by its exit status
        try:
            labels = voted(real, settings, 20, threads=2)
            os._exit(0 if np.array_equal(labels, real["expected_knn7_search7"]) else 1)
        finally:
            os._exit(2)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        done, status = os.waitpid(child, os.WNOHANG)
        if done:
            assert os.waitstatus_to_exitcode(status) == 0
            return
        time.sleep(0.05)
    os.kill(child, signal.SIGKILL)
    os.waitpid(child, 0)
    pytest.fail("the forked child's vote did not finish within 60 s")


def test_torchs_thread_count_is_used_and_left_alone(real):
    threads = torch.get_num_threads()
    try:
        for count in (2, 1):
            torch.set_num_threads(count)
            assert np.array_equal(refine(*inputs(real)), real["expected_knn7_search7"])
            assert torch.get_num_threads() == count
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("broken", ["nan pixel", "infinite point", "nan point"])
def test_ranges_that_are_not_numbers_are_left_to_the_torch_rule(monkeypatch, broken):
    data = random_scan(7, 12, 40, 800, 5)
    projected = int(np.flatnonzero(data["proj_x"] >= 0)[0])
    if broken == "nan pixel":
        data["proj_range"][3, 5] = np.nan
    else:
        data["unproj_range"][projected] = np.inf if broken == "infinite point" else np.nan
    settings = KnnSettings(5, 5, 1.0, 1.0)
    assert voted(data, settings, 5) is None
    result = batch_refined([data], settings, 5)
    torch_rule_only(monkeypatch)
    assert torch.equal(result, batch_refined([data], settings, 5))


def test_more_voters_than_the_library_keeps_are_left_to_the_torch_rule():
    data = random_scan(2, 12, 40, 400, 5)
    settings = KnnSettings(70, 9, 1.0, 1.0)  # 69 neighbours to keep, of 80
    assert voted(data, settings, 5) is None
    expected = reference(data, 70, 9, 1.0, 1.0, 5)
    assert np.array_equal(refine(*inputs(data), k=70, search=9, num_classes=5), expected)


@pytest.mark.parametrize(("column", "row"), [(40, 0), (0, 12), (0, -1), (39, 2**40)])
def test_a_pixel_outside_the_image_is_refused_not_read(column, row):
    data = random_scan(3, 12, 40, 50, 5)
    data["proj_x"][17], data["proj_y"][17] = column, row
    with pytest.raises(ValueError, match="outside the 12 x 40 range image"):
        voted(data, KnnSettings(5, 5, 1.0, 1.0), 5)


def test_arrays_of_other_lengths_or_shapes_are_refused_not_read():
    data = random_scan(3, 12, 40, 50, 5)
    settings = KnnSettings(5, 5, 1.0, 1.0)
    short = dict(data, proj_y=data["proj_y"][:-1])
    with pytest.raises(ValueError, match="50 results, 50 ranges, 50 proj_x and 49 proj_y"):
        voted(short, settings, 5)
    with pytest.raises(ValueError, match=r"classes of shape \(12, 39\) for a range image"):
        voted(dict(data, proj_argmax=data["proj_argmax"][:, 1:]), settings, 5)


def test_narrow_class_arrays_give_the_same_labels(real):
    settings = KnnSettings(7, 7, 1.0, 1.0)
    narrow = dict(real, proj_argmax=real["proj_argmax"].astype(np.uint8))
    assert np.array_equal(voted(narrow, settings, 300), voted(real, settings, 300))


def test_a_result_it_cannot_write_in_place_is_refused():
    data = random_scan(3, 12, 40, 50, 5)
    result = np.zeros(100, dtype=np.int64)[::2]
    with pytest.raises(TypeError, match="contiguous int64"):
        knn_native.vote_on_cpu(
            result,
            data["proj_argmax"],
            data["proj_range"],
            data["unproj_range"],
            data["proj_x"],
            data["proj_y"],
            KnnSettings(5, 5, 1.0, 1.0),
            5,
            1,
        )


def test_the_network_gives_the_smallest_in_order():
    rng = np.random.default_rng(3)
    values = torch.from_numpy(rng.integers(-5, 5, (9, 40)).astype(np.int16))
    for count in (1, 3, 8, 10):
        rows = torch.cat([values[:4], values[5:]])
        got = knn_rule.smallest(rows, count, 99)
        rest = torch.cat([rows, torch.full((max(0, count - 8), 40), 99)])
        expected = rest.to(torch.int16).sort(0).values[:count]
        assert torch.equal(got, expected), count


def test_a_batch_with_a_scan_of_no_points_never_leaves_the_compiled_vote(monkeypatch):
    scans = [random_scan(seed, 12, 40, 300, 5) for seed in (1, 2)]
    empty = {name: value[:0] for name, value in random_scan(3, 12, 40, 10, 5).items()}
    empty.update(proj_range=scans[0]["proj_range"], proj_argmax=scans[0]["proj_argmax"])
    settings = KnnSettings(5, 5, 1.0, 1.0)
    expected = np.concatenate([voted(s, settings, 5) for s in scans])

    def no_torch_rule(*args, **kwargs):
        raise AssertionError("the torch rule ran")

    monkeypatch.setattr(knn, "_exact", no_torch_rule)
    result = batch_refined([scans[0], empty, scans[1]], settings, 5)
    assert np.array_equal(result.numpy(), expected)


def test_the_way_it_votes_is_described_for_people(monkeypatch, tmp_path):
    isa = knn_native.best_isa()
    lanes = {1: 4, 2: 8, 3: 16}[isa]
    assert knn_native.describe() == (
        f"the compiled vote, {knn_native.ISA_NAMES[isa]} ({lanes} points a vector)"
    )
    assert knn_native.describe("cuda:1") == "the exact rule in torch on cuda:1"
    monkeypatch.setattr(knn_native, "_library", lambda: knn_native._load((tmp_path,)))
    assert knn_native.describe() == (
        "the exact rule in torch: the compiled vote is not built (no C compiler at install)"
    )


def test_a_copy_of_the_sources_first_on_the_path_takes_the_installed_library(tmp_path):
    """A Ray job runs from an uploaded copy of the sources, which holds no compiled file: the
    copy's module finds the library the interpreter's installed package was built with."""
    copy = tmp_path / "job"
    shutil.copytree(
        Path(knn_native.__file__).parents[1],
        copy / "rangeret",
        ignore=shutil.ignore_patterns("*.so", "__pycache__"),
    )
    probe = (
        "from rangeret.inference import knn_native as k; "
        "print(k.__file__); print(k._library()._name); print(k.describe())"
    )
    env = {**os.environ, "PYTHONPATH": str(copy)}
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=copy, env=env, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert out[0].startswith(str(copy)), out
    assert not out[1].startswith(str(copy)) and Path(out[1]).name.startswith("_knn_vote"), out
    assert out[2] == knn_native.describe()


def test_a_library_of_another_version_or_another_library_is_left_out(tmp_path, caplog):
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    built = {}
    for name, code in [
        ("older", "int rangeret_knn_abi(void) { return 99; }"),
        ("unrelated", "int something_else(void) { return 0; }"),
    ]:
        (tmp_path / f"{name}.c").write_text(code + "\n")
        built[name] = tmp_path / name / f"_knn_vote{suffix}"
        built[name].parent.mkdir()
        cc = ["cc", "-shared", "-fPIC", "-o", str(built[name]), str(tmp_path / f"{name}.c")]
        subprocess.run(cc, check=True)
    installed = Path(knn_native._library()._name)
    with caplog.at_level("INFO", logger=knn_native.__name__):
        assert knn_native._opened(built["older"]) is None
        assert knn_native._opened(built["unrelated"]) is None
        assert knn_native._load((built["older"].parent, built["unrelated"].parent)) is None
        folders = (built["older"].parent, installed.parent)
        assert knn_native._load(folders) is not None
    said = " ".join(r.getMessage() for r in caplog.records)
    assert f"{built['older']} is version 99, not {knn_native.ABI}" in said
    assert f"{built['unrelated']} is left out" in said
    assert f"compiled vote comes from {installed}" in said
