"""The benchmark registry: profiles name their entry (or keep the meaning they had without one),
unknown names and layouts a benchmark cannot take are one sentence, and `profile show` prints
the name."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from rangeret.cli.main import main
from rangeret.dataset.profiles import DatasetProfile, ProfileError, load_profile
from rangeret.evaluation.metrics import ConfusionMatrix
from rangeret.evaluation.scoring import DEVKIT_SCORING, SERVER_SCORING, scoring_named
from rangeret.submission.benchmarks import (
    NO_BENCHMARK,
    benchmark_of,
    no_archive_reason,
    registered,
)
from rangeret.submission.kitti_benchmark import SemanticKittiBenchmark
from rangeret.submission.nuscenes_benchmark import NuScenesLidarsegBenchmark


@pytest.mark.parametrize(
    ("name", "benchmark"),
    [
        ("semantickitti", "semantickitti"),
        ("nuscenes", "nuscenes-lidarseg"),
        ("pandaset", None),
        ("semantic-poss", None),
    ],
)
def test_profile_show_prints_the_benchmark_of_each_builtin(name, benchmark, capsys):
    assert main(["profile", "show", name]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["benchmark"]["name"] == benchmark
    assert load_profile(name).benchmark.name == benchmark


def _without_name(profile: DatasetProfile, **changes) -> dict:
    data = profile.to_dict()
    del data["benchmark"]["name"]
    data.update(changes)
    return data


def test_a_profile_written_before_benchmark_names_keeps_its_meaning():
    nuscenes = DatasetProfile.from_dict(_without_name(load_profile("nuscenes"), name="my-nu"))
    assert isinstance(benchmark_of(nuscenes), NuScenesLidarsegBenchmark)
    kitti = DatasetProfile.from_dict(_without_name(load_profile("semantickitti")))
    assert isinstance(benchmark_of(kitti), SemanticKittiBenchmark)
    renamed = DatasetProfile.from_dict(_without_name(load_profile("semantickitti"), name="mine"))
    assert benchmark_of(renamed) is NO_BENCHMARK
    old = load_profile("semantickitti").to_dict()
    del old["benchmark"]
    assert benchmark_of(DatasetProfile.from_dict(old)) is benchmark_of(kitti)
    assert no_archive_reason(renamed) is not None and no_archive_reason(kitti) is None


def test_a_profile_may_name_no_benchmark_or_another_one():
    data = load_profile("semantickitti").to_dict()
    data["benchmark"]["name"] = None
    assert benchmark_of(DatasetProfile.from_dict(data)) is NO_BENCHMARK
    data["name"], data["benchmark"]["name"] = "kitti-copy", "semantickitti"
    assert isinstance(benchmark_of(DatasetProfile.from_dict(data)), SemanticKittiBenchmark)
    data["benchmark"]["name"] = " "
    with pytest.raises(ProfileError, match=r"benchmark.name: must name a benchmark"):
        DatasetProfile.from_dict(data)


def test_an_unknown_benchmark_or_a_layout_it_cannot_take_is_one_sentence():
    data = load_profile("pandaset").to_dict()
    data["benchmark"]["name"] = "waymo"
    with pytest.raises(ProfileError, match=r"'waymo' is not a known benchmark; known: "):
        benchmark_of(DatasetProfile.from_dict(data))
    data["benchmark"]["name"] = "nuscenes-lidarseg"
    with pytest.raises(ProfileError, match=r"takes a version's tables, not folders"):
        benchmark_of(DatasetProfile.from_dict(data))
    nu = load_profile("nuscenes").to_dict()
    nu["benchmark"]["name"] = "semantickitti"
    with pytest.raises(ProfileError, match=r"takes folders of sequences"):
        benchmark_of(DatasetProfile.from_dict(nu))


def test_the_builtins_come_first_and_cannot_be_replaced():
    assert list(registered())[:2] == ["semantickitti", "nuscenes-lidarseg"]
    assert all(b.writes_archives for b in registered().values())
    assert not NO_BENCHMARK.writes_archives


def test_the_two_scorings_differ_where_the_evaluators_do():
    matrix = np.array([[5, 2, 0], [1, 3, 0], [0, 0, 0]])
    server = ConfusionMatrix(3, (0,), matrix, "semantickitti")
    devkit = ConfusionMatrix(3, (0,), matrix, DEVKIT_SCORING)
    assert server.scoring is SERVER_SCORING and devkit.scoring is scoring_named("nuscenes")
    # class 2 is absent from both sides: 0 for the server's mean, left out by the devkit's
    assert server.iou()[2] == 0 and np.isnan(devkit.iou()[2])
    # the devkit also drops predictions of the ignored class 0: class 1 loses its 2 misses
    assert server.iou()[1] == pytest.approx(3 / 5) and devkit.iou()[1] == pytest.approx(1.0)
    assert server.miou() == pytest.approx((3 / 5 + 0) / 2) and devkit.miou() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="scoring must be one of semantickitti, nuscenes"):
        ConfusionMatrix(3, (0,), matrix, "waymo")
