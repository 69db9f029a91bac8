"""kNN refinement (`rangeret.knn.refine`, over `rangeret.inference.knn.refine_batch`): the
published output, the rule itself, types, errors.

The published post-processing's output on a real scan (`tests/data/knn-semantickitti-scan.npz`)
is the main check; a slow per-point version of the rule written directly from the rule checks
everything else, ties included, on random images. A batch (`refine_batch`) must give each scan's
`refine` result bit for bit (`test_knn_batch.py`). Every test here runs twice on the CPU: with the
compiled vote and with the exact rule in torch (the devices' path); `test_knn_native.py` checks
the compiled vote's own cases.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rangeret.inference import knn
from rangeret.inference.knn import gaussian_kernel
from rangeret.inference.settings import KnnSettings
from rangeret.knn import refine
from tests.support.paths import data_path

FIXTURE = "knn-semantickitti-scan.npz"
INPUTS = ("proj_range", "unproj_range", "proj_argmax", "proj_x", "proj_y")
PUBLISHED = {(7, 7): "expected_knn7_search7", (5, 5): "expected_knn5_search5"}


@pytest.fixture(autouse=True, params=["compiled", "torch"])
def cpu_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Each test with the compiled vote, then with the exact rule in torch on the CPU."""
    if request.param == "torch":
        torch_rule_only(monkeypatch)
    return request.param


def torch_rule_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """Turn the compiled vote off: the CPU runs the exact rule in torch, as devices do."""
    monkeypatch.setattr(knn, "vote_on_cpu", lambda *args, **kwargs: False)


@pytest.fixture(scope="module")
def scan() -> dict[str, np.ndarray]:
    """The fixture's arrays."""
    with np.load(data_path(FIXTURE)) as data:
        return {name: data[name] for name in data.files}


@pytest.fixture(scope="module")
def refined(scan: dict[str, np.ndarray]) -> dict[tuple[int, int], np.ndarray]:
    """`refine` on the fixture for both published parameter sets (k, search), computed once by
    the path of the first test that asks (the other path must match it)."""
    return {
        (k, search): refine(*inputs(scan), k=k, search=search, sigma=1.0, cutoff=1.0)
        for k, search in PUBLISHED
    }


def inputs(scan: dict[str, np.ndarray]) -> list[np.ndarray]:
    """The five arrays `refine` takes, in its order."""
    return [scan[name] for name in INPUTS]


def window_distances(
    scan: dict[str, np.ndarray], point: int, search: int, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Distances (float32, centre at 0) and classes of one point's window, in window order."""
    pad = search // 2
    ranges = np.pad(
        np.where(scan["proj_range"] < 0, np.float32(np.inf), scan["proj_range"]).astype(np.float32),
        pad,
    )
    classes = np.pad(scan["proj_argmax"], pad)
    y, x = scan["proj_y"][point], scan["proj_x"][point]
    own = np.float32(scan["unproj_range"][point])
    window = ranges[y : y + search, x : x + search].reshape(-1).copy()
    window[search * search // 2] = own
    weights = (1 - gaussian_kernel(search, sigma).numpy()).reshape(-1)
    dist = (np.abs(window - own) * weights).astype(np.float32)
    return dist, classes[y : y + search, x : x + search].reshape(-1)


def reference(
    scan: dict[str, np.ndarray],
    k: int,
    search: int,
    sigma: float,
    cutoff: float,
    num_classes: int,
    votes_from: int = 1,
    unprojected: int = 0,
) -> np.ndarray:
    """The refinement rule point by point; ties at the k-th place in window order; classes
    votes_from..C-1 vote (the zero padding is class 0)."""
    out = np.full(len(scan["unproj_range"]), unprojected, dtype=np.int64)
    centre = search * search // 2
    for point in np.flatnonzero(scan["proj_x"] >= 0):
        dist, classes = window_distances(scan, point, search, sigma)
        rank = dist.copy()
        rank[centre] = -1  # the centre always takes a place
        nearest = np.argsort(rank, kind="stable")[:k]
        if cutoff > 0:
            nearest = nearest[dist[nearest] <= cutoff]
        votes = np.bincount(classes[nearest], minlength=num_classes)[votes_from:]
        # first maximum: the lowest class; no vote at all: class `votes_from`
        out[point] = votes.argmax() + votes_from
    return out


def kth_place_is_tied(
    scan: dict[str, np.ndarray], point: int, k: int, search: int, sigma: float, cutoff: float
) -> bool:
    """Whether the k-th and (k+1)-th smallest distances are equal and the tie can vote."""
    dist = np.sort(window_distances(scan, point, search, sigma)[0])
    if k >= len(dist) or dist[k - 1] != dist[k]:
        return False
    return cutoff <= 0 or dist[k - 1] <= cutoff


def random_scan(
    seed: int, height: int = 6, width: int = 20, points: int = 300, num_classes: int = 5
) -> dict[str, np.ndarray]:
    """A small random scan with empty pixels and many equal distances (ranges on a 0.25 grid)."""
    rng = np.random.default_rng(seed)
    image = (rng.integers(1, 24, (height, width)) * 0.25).astype(np.float32)
    image[rng.random((height, width)) < 0.2] = -1
    proj_y = rng.integers(0, height, points)
    proj_x = rng.integers(0, width, points)
    own = np.where(
        rng.random(points) < 0.5,
        image[proj_y, proj_x],
        rng.integers(1, 24, points) * 0.25,
    ).astype(np.float32)
    own = np.where(own < 0, np.float32(1.5), own)
    proj_x[rng.random(points) < 0.05] = -1
    return scan_arrays(image, own, rng.integers(0, num_classes, (height, width)), proj_x, proj_y)


def scan_arrays(
    image: np.ndarray, own: np.ndarray, argmax: np.ndarray, proj_x: np.ndarray, proj_y: np.ndarray
) -> dict[str, np.ndarray]:
    """A scan's arrays by name, proj_y -1 wherever proj_x is (a point without a pixel)."""
    return {
        "proj_range": image,
        "unproj_range": own,
        "proj_argmax": argmax,
        "proj_x": proj_x,
        "proj_y": np.where(proj_x < 0, -1, proj_y),
    }


def test_gaussian_kernel_is_a_normalised_centred_gaussian():
    kernel = gaussian_kernel(5, 1.5)
    assert kernel.shape == (5, 5) and kernel.dtype == torch.float32
    kernel = kernel.double()
    assert kernel.sum().item() == pytest.approx(1.0, abs=1e-6)
    assert torch.equal(kernel, kernel.T) and torch.equal(kernel, kernel.flip(0))
    assert kernel.argmax().item() == 12
    # exp(-(dx^2 + dy^2) / (2 sigma^2)) relative to the centre
    assert (kernel[2, 4] / kernel[2, 2]).item() == pytest.approx(np.exp(-4 / 4.5), rel=1e-6)
    assert (kernel[0, 0] / kernel[2, 2]).item() == pytest.approx(np.exp(-8 / 4.5), rel=1e-6)
    assert gaussian_kernel(1, 1.0).tolist() == [[1.0]]


@pytest.mark.parametrize(("k", "search"), [(7, 7), (5, 5)])
def test_matches_the_published_output(scan, refined, k, search):
    expected = scan[PUBLISHED[k, search]]
    result = refined[k, search]
    differ = np.flatnonzero(result != expected)
    assert 1 - len(differ) / len(expected) >= 0.999
    # The published top-k is arbitrary only among equal distances: any difference must be there.
    untied = [p for p in differ if not kth_place_is_tied(scan, p, k, search, 1.0, 1.0)]
    assert untied == [], f"{len(untied)} of {len(differ)} differences are not at a tie"


def test_refinement_recovers_the_ground_truth(scan, refined):
    labelled = scan["gt"] > 0
    noisy = scan["proj_argmax"][scan["proj_y"], scan["proj_x"]]
    result = refined[7, 7]
    assert (noisy[labelled] == scan["gt"][labelled]).mean() == pytest.approx(0.784, abs=1e-3)
    assert (result[labelled] == scan["gt"][labelled]).mean() >= 0.95


def test_chunk_size_does_not_change_the_result(scan, refined):
    small = refine(*inputs(scan), chunk_size=1000)
    assert np.array_equal(small, refine(*inputs(scan), chunk_size=10**9))
    assert np.array_equal(small, refined[7, 7])


def test_numpy_in_numpy_out_and_torch_in_torch_out():
    data = random_scan(0)
    arrays = refine(*inputs(data))
    assert isinstance(arrays, np.ndarray)
    assert arrays.dtype == np.int64 and arrays.shape == (300,)
    tensors = refine(*[torch.from_numpy(data[name]) for name in INPUTS])
    assert isinstance(tensors, torch.Tensor)
    assert tensors.dtype == torch.int64 and tensors.device.type == "cpu"
    assert np.array_equal(tensors.numpy(), arrays)
    # One tensor among numpy arrays is enough for a tensor result.
    mixed = refine(*inputs(data)[:2], torch.from_numpy(data["proj_argmax"]), *inputs(data)[3:])
    assert isinstance(mixed, torch.Tensor) and np.array_equal(mixed.numpy(), arrays)


def test_unprojected_points_get_class_zero(scan, refined):
    data = dict(scan)
    dropped = np.arange(0, len(data["proj_x"]), 97)
    data["proj_x"] = data["proj_x"].copy()
    data["proj_y"] = data["proj_y"].copy()
    data["proj_x"][dropped] = -1
    data["proj_y"][dropped] = -1
    result = refine(*inputs(data))
    assert (result[dropped] == 0).all()
    kept = np.setdiff1d(np.arange(len(result)), dropped)
    assert np.array_equal(result[kept], refined[7, 7][kept])
    everything = dict(data, proj_x=np.full_like(data["proj_x"], -1))
    assert (refine(*inputs(everything)) == 0).all()


def test_a_hand_made_image():
    # search 3, k 3, sigma 1: weights 1 - g with g = 0.2042 (centre), 0.1238 (edge), 0.0751 (corner),
    # so a neighbour's distance is about 0.876 |dr| on an edge and 0.925 |dr| on a corner.
    image = np.array([[10.1, 30.0, 10.2], [30.0, 10.0, 30.0], [-1.0, 30.0, 30.0]], dtype=np.float32)
    classes = np.array([[4, 1, 3], [1, 7, 1], [0, 1, 1]])
    points = {
        # centre 7; nearest 10.1 (class 4, d 0.09) and 10.2 (class 3, d 0.18): one vote each,
        # the tie goes to the lowest class id, 3.
        "tie": (1, 1, 10.0, 3),
        # on the empty pixel (class 0, abstains), range 50: every neighbour, the zero padding
        # below and to the left included (range 0: d = 50 w), is beyond the cutoff -> class 1.
        "no vote": (2, 0, 50.0, 1),
        # centre 7; the four edges at 30.0 tie (d 0.044) and all say 1: 1 wins with 2 votes.
        "tied place": (1, 1, 30.05, 1),
        "not projected": (-1, -1, 5.0, 0),
    }
    rows, cols, ranges, expected = (
        np.array(column) for column in zip(*points.values(), strict=True)
    )
    result = refine(
        image, ranges.astype(np.float32), classes, cols, rows, k=3, search=3, cutoff=1.0
    )
    assert dict(zip(points, result.tolist(), strict=True)) == dict(
        zip(points, expected.tolist(), strict=True)
    )


def test_zero_padding_takes_places_and_does_not_vote():
    # A point of range 0.6 in the top row: the padding above it (range 0) is at 0.6 * 0.876 = 0.53
    # (edge) and 0.6 * 0.925 = 0.55 (corners), nearer than its neighbours 1.25 (edge, d 0.57) and
    # 1.3 (d 0.61), both class 4. With k 3 the two places go to padding, which abstains, so the
    # centre's class 2 stays; with k 6 the two class-4 pixels get in and win.
    image = np.array([[1.25, 0.6, 1.3], [5.0, 5.0, 5.0], [5.0, 5.0, 5.0]], dtype=np.float32)
    classes = np.array([[4, 2, 4], [3, 3, 3], [3, 3, 3]])
    args = (image, np.array([0.6], dtype=np.float32), classes, np.array([1]), np.array([0]))
    assert refine(*args, k=3, search=3).tolist() == [2]
    assert refine(*args, k=6, search=3).tolist() == [4]


def test_no_wrap_around_in_azimuth():
    # The point sits in column 0; column W-1 (range 5, class 9) would be its nearest neighbour if
    # the window wrapped. Without wrap its left neighbours are padding (d ~ 4.4) and everything
    # else is 15 away, beyond the cutoff; the centre abstains (class 0): class 1.
    image = np.array([[20.0, 20.0, 5.0], [5.0, 20.0, 5.0], [20.0, 20.0, 5.0]], dtype=np.float32)
    classes = np.array([[1, 1, 9], [0, 1, 9], [1, 1, 9]])
    args = (image, np.array([5.0], dtype=np.float32), classes, np.array([0]), np.array([1]))
    assert refine(*args, k=3, search=3).tolist() == [1]


@pytest.mark.parametrize(
    ("k", "search", "sigma", "cutoff", "num_classes"),
    [
        (1, 1, 1.0, 1.0, 5),
        (1, 5, 1.0, 1.0, 5),
        (3, 3, 1.0, 1.0, 5),
        (9, 3, 1.0, 1.0, 5),
        (9, 3, 1.0, 0.0, 5),
        (5, 5, 1.0, 1.0, 5),
        (5, 5, 2.0, 0.0, 5),
        (7, 7, 1.0, 1.0, 5),
        (7, 7, 1.0, -1.0, 3),
        (12, 7, 0.5, 2.0, 5),
        (49, 7, 1.0, 2.0, 5),
        (10, 13, 1.0, 1.5, 300),
    ],
)
def test_matches_the_rule_on_random_images(k, search, sigma, cutoff, num_classes):
    for seed in range(3):
        data = random_scan(seed, num_classes=num_classes)
        expected = reference(data, k, search, sigma, cutoff, num_classes)
        result = refine(*inputs(data), k, search, sigma, cutoff, num_classes, chunk_size=37)
        assert np.array_equal(result, expected), f"seed {seed}"


@pytest.mark.parametrize(
    ("k", "search", "cutoff", "num_classes", "unprojected"),
    [
        (1, 1, 1.0, 5, 4),
        (3, 3, 1.0, 5, 4),
        (7, 7, 1.0, 15, 14),
        (9, 3, 0.0, 15, 14),
        (7, 7, 1.0, 3, 2),
    ],
)
def test_every_class_may_win_where_class_0_is_real(k, search, cutoff, num_classes, unprojected):
    """PandaSet's rule: class 0 (car) votes, a point without a vote gets class 0, and points
    without a pixel get the unlabeled class (the last one)."""
    for seed in range(3):
        data = random_scan(seed, num_classes=num_classes)
        expected = reference(data, k, search, 1.0, cutoff, num_classes, 0, unprojected)
        result = refine(
            *inputs(data),
            k,
            search,
            1.0,
            cutoff,
            num_classes,
            votes_from=0,
            unprojected=unprojected,
            chunk_size=37,
        )
        assert np.array_equal(result, expected), f"seed {seed}"
        assert (result[data["proj_x"] < 0] == unprojected).all()


def test_class_0_wins_only_where_it_may():
    # Neighbours of class 0 outvote the centre's class 2 under PandaSet's rule, not SemanticKITTI's.
    image = np.full((3, 3), 5.0, dtype=np.float32)
    classes = np.array([[0, 0, 0], [0, 2, 0], [3, 3, 3]])
    args = (image, np.array([5.0], dtype=np.float32), classes, np.array([1]), np.array([1]))
    assert refine(*args, k=9, search=3, num_classes=4).tolist() == [3]
    assert refine(*args, k=9, search=3, num_classes=4, votes_from=0).tolist() == [0]


def test_bad_arguments_are_named():
    data = random_scan(1)
    args = inputs(data)
    cases = [
        ({"search": 4}, "search"),
        ({"search": 0}, "search"),
        ({"k": 0}, "k"),
        ({"k": 10, "search": 3}, "k"),
        ({"sigma": 0.0}, "sigma"),
        ({"cutoff": float("nan")}, "cutoff"),
        ({"num_classes": 1}, "num_classes"),
        ({"chunk_size": 0}, "chunk_size"),
    ]
    for kwargs, name in cases:
        with pytest.raises(ValueError, match=name):
            refine(*args, **kwargs)
    bad_inputs = [
        (0, args[0][0], "proj_range"),
        (2, args[2][:-1], "proj_argmax"),
        (2, args[2] + 20, "proj_argmax"),
        (2, args[2] - 1, "proj_argmax"),
        (2, args[2].astype(np.float32), "proj_argmax"),
        (1, args[1][:-1], "unproj_range"),
        (1, args[1][:, None], "unproj_range"),
        (3, np.where(args[3] == 0, 20, args[3]), "proj_x"),
        (3, args[3] - 2, "proj_x"),
        (4, np.where(args[3] >= 0, args[4] + 6, -1), "proj_y"),
        (4, args[4][:-1], "proj_y"),
    ]
    for position, value, name in bad_inputs:
        broken = list(args)
        broken[position] = value
        with pytest.raises(ValueError, match=name):
            refine(*broken)


def test_knn_settings_are_checked_when_made():
    cases = [
        ({"search": 4}, "search"),
        ({"search": 1.0}, "search"),
        ({"k": True}, "k"),
        ({"k": 50}, "k"),
        ({"sigma": float("nan")}, "sigma"),
        ({"cutoff": "1"}, "cutoff"),
    ]
    for kwargs, name in cases:
        with pytest.raises(ValueError, match=f"^{name} must"):
            KnnSettings(**kwargs)
    assert KnnSettings(k=np.int64(49), search=np.int32(7), cutoff=-1.0).k == 49


def test_unusable_inputs_are_named_not_a_traceback():
    data = random_scan(1)
    args = inputs(data)
    cases = [
        (0, torch.from_numpy(args[0]).to(torch.bfloat16), "proj_range"),
        (0, args[0].astype(np.complex64), "proj_range"),
        (3, args[3] >= 0, "proj_x"),
        (4, [str(v) for v in args[4]], "proj_y"),
        (2, np.zeros((0, 0), dtype=np.int64), "proj_argmax"),
        (0, np.float32(1.0), "proj_range"),
    ]
    for position, value, name in cases:
        broken = list(args)
        broken[position] = value
        with pytest.raises(ValueError, match=name):
            refine(*broken)
    for name, value in (("votes_from", 20), ("unprojected", -1), ("num_classes", 2.0)):
        with pytest.raises(ValueError, match=name):
            refine(*args, **{name: value})


def test_tensors_on_different_devices_are_refused():
    data = random_scan(1)
    tensors = [torch.from_numpy(data[name]) for name in INPUTS]
    tensors[2] = tensors[2].to("meta")
    with pytest.raises(ValueError, match="different devices"):
        refine(*tensors)


def test_inputs_are_left_untouched():
    data = random_scan(2)
    tensors = [torch.from_numpy(data[name].copy()) for name in INPUTS]
    refine(*tensors)
    for name, tensor in zip(INPUTS, tensors, strict=True):
        assert np.array_equal(tensor.numpy(), data[name]), name


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    cases = [random_scan(seed) for seed in range(3)]
    with np.load(data_path(FIXTURE)) as fixture:
        cases.append({name: fixture[name] for name in INPUTS})
    for data in cases:
        for k, search, cutoff in [(7, 7, 1.0), (5, 5, 1.0), (9, 3, 0.0)]:
            cpu = refine(
                *[torch.from_numpy(data[n]) for n in INPUTS], k=k, search=search, cutoff=cutoff
            )
            cuda = refine(
                *[torch.from_numpy(data[n]).cuda() for n in INPUTS],
                k=k,
                search=search,
                cutoff=cutoff,
            )
            assert cuda.device.type == "cuda"
            assert torch.equal(cuda.cpu(), cpu)
