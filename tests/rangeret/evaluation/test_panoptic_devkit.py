"""`rangeret.evaluation.panoptic` under the nuScenes devkit's rules against the devkit's own
`PanopticEval` (`nuscenes-devkit` 1.2.0, run in its venv by `tests/support/devkit_check.py`): the
same counts, every per-class score and the segmentation results dict `NuScenesPanopticEval`
wraps them in, to 1e-9.

The scans are panoptic values as the devkit reads them (1000 * class + instance, uint16): the
ground truth's fine classes through the challenge's class map, the predictions' classes as they
are, and the whole value as the instance id.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.profiles import load_profile
from rangeret.evaluation.panoptic import DEVKIT_PANOPTIC, KITTI_PANOPTIC, PanopticCounts
from tests.support.devkit import run_devkit

pytestmark = pytest.mark.slow

TOL = 1e-9
LABELS = load_profile("nuscenes").labels
NAMES = list(LABELS.class_names)
IGNORE = [c for c in range(LABELS.num_classes) if LABELS.ignored[c]]
#: Fine class index -> challenge class, as the devkit's class mapper maps them.
FINE_TO_CLASS = np.array([LABELS.raw_to_class[f] for f in range(32)], dtype=np.int64)
THING_FINE = [f for f in range(32) if 1 <= FINE_TO_CLASS[f] <= 10]
STUFF_FINE = [f for f in range(32) if FINE_TO_CLASS[f] >= 11]
IGNORED_FINE = [f for f in range(32) if FINE_TO_CLASS[f] == 0]

#: A scan: predicted and ground-truth panoptic values (1000 * class + instance).
Scan = tuple[np.ndarray, np.ndarray]


def values(cls: int, instance: int, n: int) -> np.ndarray:
    """`n` panoptic values of one class and instance."""
    return np.full(n, 1000 * cls + instance, dtype=np.uint16)


def random_scan(rng: np.random.Generator) -> Scan:
    """Ground-truth segments of every kind (fine classes) and a prediction (challenge classes)
    that keeps, splits, merges, relabels, shrinks or misses each, with ignored points and noise."""
    gt_parts: list[np.ndarray] = []
    pred_parts: list[np.ndarray] = []
    merged: dict[int, int] = {}
    absent = set(rng.choice(np.arange(1, 17), size=3, replace=False).tolist())
    things = [f for f in THING_FINE if FINE_TO_CLASS[f] not in absent]
    stuff = [f for f in STUFF_FINE if FINE_TO_CLASS[f] not in absent]
    sizes = [2, 8, 14, 15, 16, 30, 49, 50, 51, 150, 400]
    segments = [(int(rng.choice(things)), int(rng.integers(1, 999))) for _ in range(14)]
    segments += [(f, 0) for f in stuff] + [(int(rng.choice(stuff)), int(rng.integers(1, 4)))]
    for fine, instance in segments:
        n = int(rng.choice(sizes)) if instance else int(rng.integers(20, 700))
        cls = int(FINE_TO_CLASS[fine])
        gt = values(fine, instance, n)
        mine = int(rng.integers(1, 999)) if instance else 0
        pred = values(cls, mine, n)
        kind = rng.choice(["keep", "split", "merge", "swap", "shrink", "miss", "stuff-ids"])
        if kind == "split":
            pred[int(rng.integers(0, n + 1)) :] = 1000 * cls + int(rng.integers(1, 999))
        elif kind == "merge":
            pred[:] = 1000 * cls + merged.setdefault(cls, mine)
        elif kind == "swap":
            pred[:] = 1000 * int(rng.integers(1, 17)) + mine
        elif kind == "shrink":
            lost = rng.random(n) < rng.uniform(0.1, 0.7)
            pred[lost] = 1000 * rng.integers(0, 17, size=int(lost.sum())).astype(np.uint16)
        elif kind == "miss":
            pred[:] = 0
        elif kind == "stuff-ids":
            pred[:] = 1000 * cls + rng.integers(0, 3, size=n).astype(np.uint16)
        gt_parts.append(gt)
        pred_parts.append(pred)
    k = int(rng.integers(1, 300))
    gt_parts.append((1000 * rng.choice(IGNORED_FINE, size=k)).astype(np.uint16))
    pred_parts.append(1000 * rng.integers(0, 17, size=k) + rng.integers(0, 3, size=k))
    gt_parts.append(values(0, 0, 40))
    pred_parts.append(values(4, 321, 40))
    for n in (14, 15, 16, 60):
        gt_parts.append(values(int(rng.choice(stuff)), 0, n))
        pred_parts.append(values(int(FINE_TO_CLASS[rng.choice(things)]), 900 + n, n))
    gt = np.concatenate(gt_parts).astype(np.uint16)
    pred = np.concatenate(pred_parts).astype(np.uint16)
    noisy = rng.random(gt.size) < 0.02
    pred[noisy] = rng.choice(pred, size=int(noisy.sum()))
    order = rng.permutation(gt.size)
    return pred[order], gt[order]


def as_devkit(scan: Scan) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What `NuScenesPanopticEval` hands its evaluator for a scan: predicted classes and
    instances, ground-truth classes and instances."""
    pred, gt = scan
    return pred // 1000, pred, FINE_TO_CLASS[gt // 1000], gt


def devkit_arrays(folder: Path, scans: list[Scan], min_points: int | None = None) -> dict:
    """The devkit's `PanopticEval` over the scans (`devkit_check.py panoptic-arrays`)."""
    arrays: dict[str, np.ndarray] = {"scans": np.array(len(scans))}
    if min_points is not None:
        arrays["min_points"] = np.array(min_points)
    for k, scan in enumerate(scans):
        pc, pi, gc, gi = as_devkit(scan)
        arrays |= {
            f"pred_class_{k}": pc,
            f"pred_instance_{k}": pi,
            f"gt_class_{k}": gc,
            f"gt_instance_{k}": gi,
        }
    path = folder / f"scans-{len(list(folder.iterdir()))}.npz"
    np.savez(path, **arrays)
    return run_devkit("panoptic-arrays", "--input", path)


def ours_over(scans: list[Scan], min_points: int | None = None) -> PanopticCounts:
    """Our counter under the devkit's rules over the scans."""
    counts = PanopticCounts.for_classes(NAMES, IGNORE, DEVKIT_PANOPTIC, min_points=min_points)
    for scan in scans:
        counts.add(*as_devkit(scan))
    return counts


def assert_same(theirs: dict, ours: PanopticCounts) -> None:
    """Equal counts, per-class scores and results dict."""
    assert theirs["min_points"] == ours.min_points
    for key in ("tp", "fp", "fn", "confusion"):
        np.testing.assert_array_equal(getattr(ours, key), np.array(theirs[key]), err_msg=key)
    np.testing.assert_allclose(ours.iou_sum, theirs["iou_sum"], rtol=0, atol=TOL)
    per = ours.per_class()
    for key in ("pq", "sq", "rq", "iou"):
        np.testing.assert_allclose(per[key], theirs[key], rtol=0, atol=TOL, err_msg=key)
    summary = ours.summary(NAMES)
    results = theirs["results"]
    assert list(summary) == list(results) == ["all", *NAMES]
    for key, value in results.items():
        assert list(summary[key]) == list(value), key
        assert summary[key] == pytest.approx(value, abs=TOL), key
    means = {"PQ": "mean_pq", "SQ": "mean_sq", "RQ": "mean_rq", "mIoU": "mean_iou"}
    for key, mean in means.items():
        assert summary["all"][key] == pytest.approx(theirs[mean], abs=TOL), key


def test_random_scans_accumulated(tmp_path: Path) -> None:
    rng = np.random.default_rng(21)
    scans = [random_scan(rng) for _ in range(6)]
    ours = ours_over(scans)
    assert ours.min_points == 15
    assert_same(devkit_arrays(tmp_path, scans), ours)
    assert ours.tp.sum() > 20 and ours.fp.sum() > 20 and ours.fn.sum() > 20


@pytest.mark.parametrize("min_points", [1, 50])
def test_other_minimum_sizes(tmp_path: Path, min_points: int) -> None:
    rng = np.random.default_rng(100 + min_points)
    scans = [random_scan(rng) for _ in range(3)]
    assert_same(devkit_arrays(tmp_path, scans, min_points), ours_over(scans, min_points))


def test_constructed_cases(tmp_path: Path) -> None:
    car, ped, adult, child, road = 17, 7, 2, 3, 24
    cases = [
        # Unmatched segments just below, at and above the minimum size, on both sides.
        (
            [values(11, 0, 14), values(11, 0, 15), values(11, 0, 16)],
            [values(car, i, n) for i, n in ((1, 14), (2, 15), (3, 16))],
        ),
        ([values(4, i, n) for i, n in ((1, 14), (2, 15), (3, 16))], [values(road, 0, 45)]),
        # A matched segment far below the minimum, and a half-and-half split (no match).
        ([values(ped, 3, 4)], [values(adult, 9, 4)]),
        ([values(4, 1, 30), values(4, 2, 30)], [values(car, 7, 60)]),
        # An adult and a child of one instance number are two pedestrian segments.
        ([values(ped, 5, 100)], [values(adult, 5, 70), values(child, 5, 30)]),
        # Predictions of the ignore class, and ground truth all ignored.
        ([values(0, 0, 80)], [values(car, 1, 80)]),
        ([values(4, 1, 80)], [values(0, 0, 40), values(31, 0, 40)]),
    ]
    scans = [(np.concatenate(p), np.concatenate(g)) for p, g in cases]
    assert_same(devkit_arrays(tmp_path, scans), ours_over(scans))


def test_results_shape_and_rules(tmp_path: Path) -> None:
    theirs = devkit_arrays(tmp_path, [])
    ours = ours_over([])
    assert_same(theirs, ours)
    assert theirs["results"]["ignore"] == {"PQ": 0.0, "SQ": 0.0, "RQ": 0.0, "IoU": 0.0}
    assert list(theirs["results"]["all"]) == ["PQ", "SQ", "RQ", "mIoU", "PQ_dagger"]
    assert sorted(NAMES[c] for c in ours.things) == sorted(DEVKIT_PANOPTIC.thing_names)
    assert [NAMES[c] for c in ours.stuff] == NAMES[11:]
    # The counting is the same as SemanticKITTI's; only the rules' sizes and reports differ.
    rng = np.random.default_rng(3)
    scans = [random_scan(rng) for _ in range(2)]
    devkit = ours_over(scans, min_points=50)
    kitti = PanopticCounts(len(NAMES), IGNORE, devkit.things, KITTI_PANOPTIC)
    for scan in scans:
        kitti.add(*as_devkit(scan))
    for key in ("tp", "fp", "fn", "confusion", "iou_sum"):
        np.testing.assert_array_equal(getattr(kitti, key), getattr(devkit, key))
