"""`rangeret.evaluation.panoptic` under SemanticKITTI's rules against the SemanticKITTI
development kit's own `PanopticEval` (its copy in tests/data/reference): the same TP, FP, FN and
confusion counts, and every score, per class and every mean of `evaluate_panoptic.py`, to 1e-9.

The scans are raw `.label` values, read the way `evaluate_panoptic.py` reads them: classes
through the learning map of the official label configuration, the whole 32-bit label as the
instance id.
"""

from __future__ import annotations

import importlib.util
import re
import runpy
from collections.abc import Iterator
from functools import cache
from types import ModuleType

import numpy as np
import pytest
import yaml

from rangeret.evaluation.panoptic import KITTI_PANOPTIC, PanopticCounts
from tests.support.paths import data_path

TOL = 1e-9

#: `evaluate_panoptic.py`'s own lists, in its order.
SCRIPT_THINGS = [
    "car",
    "truck",
    "bicycle",
    "motorcycle",
    "other-vehicle",
    "person",
    "bicyclist",
    "motorcyclist",
]
SCRIPT_STUFF = [
    "road",
    "sidewalk",
    "parking",
    "other-ground",
    "building",
    "vegetation",
    "trunk",
    "terrain",
    "fence",
    "pole",
    "traffic-sign",
]
SCORES_KEYS = [
    "pq_mean",
    "pq_dagger",
    "sq_mean",
    "rq_mean",
    "iou_mean",
    "pq_stuff",
    "rq_stuff",
    "sq_stuff",
    "pq_things",
    "rq_things",
    "sq_things",
]
#: Raw ids of the official configuration by role (several map to one class: 10 and 252 are car,
#: 40 and 60 road, 13, 16, 20, 256, 257 and 259 other-vehicle).
THING_RAW = [10, 11, 13, 15, 16, 18, 20, 30, 31, 32, 252, 253, 254, 255, 256, 257, 258, 259]
STUFF_RAW = [40, 44, 48, 49, 50, 51, 60, 70, 71, 72, 80, 81]
IGNORED_RAW = [0, 1, 52, 99]


@cache
def reference() -> ModuleType:
    """The official `auxiliary/eval_np.py`, loaded from its copy."""
    path = data_path("reference", "semantic_kitti_eval_np.py")
    spec = importlib.util.spec_from_file_location("semantic_kitti_eval_np", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@cache
def config() -> tuple[np.ndarray, list[str], list[int]]:
    """The official configuration as `evaluate_panoptic.py` reads it: its lookup table, the class
    names and the ignored classes."""
    data = yaml.safe_load(data_path("semantic-kitti.yaml").read_text())
    remap = data["learning_map"]
    lut = np.zeros(max(remap) + 100, dtype=np.int32)
    lut[list(remap)] = list(remap.values())
    inv = data["learning_map_inv"]
    names = [data["labels"][inv[c]] for c in range(len(inv))]
    ignore = [c for c, ignored in data["learning_ignore"].items() if ignored]
    return lut, names, ignore


def from_labels(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Classes and instance ids of raw labels, as `evaluate_panoptic.py` takes them."""
    labels = np.asarray(labels, dtype=np.uint32)
    return config()[0][labels & 0xFFFF], labels


Scan = tuple[np.ndarray, np.ndarray]


def run_both(
    scans: list[Scan], min_points: int | None = None
) -> tuple[object, PanopticCounts, dict]:
    """The official evaluator and ours over (prediction, ground truth) label scans; the script's
    scores and ours."""
    _, names, ignore = config()
    limit = KITTI_PANOPTIC.min_points if min_points is None else min_points
    ref = reference().PanopticEval(len(names), None, ignore, min_points=limit)
    ours = PanopticCounts.for_classes(names, ignore, KITTI_PANOPTIC, min_points=min_points)
    for pred, gt in scans:
        pc, pi = from_labels(pred)
        gc, gi = from_labels(gt)
        ref.addBatch(pc, pi, gc, gi)
        ours.add(pc, pi, gc, gi)
    return ref, ours, ours.summary(names)


def script_scores(ref: object, names: list[str]) -> dict:
    """What `evaluate_panoptic.py` makes of the evaluator: the scores.txt keys, then each class of
    its lists with its PQ, SQ, RQ and IoU."""
    _, _, _, pq, sq, rq = ref.getPQ()
    miou, iou = ref.getSemIoU()
    table = {
        names[c]: {"pq": pq[c], "sq": sq[c], "rq": rq[c], "iou": iou[c]} for c in range(len(names))
    }

    def mean(key: str, classes: list[str]) -> float:
        return float(np.mean([float(table[c][key]) for c in classes]))

    named = SCRIPT_THINGS + SCRIPT_STUFF
    dagger = [float(table[c]["pq"]) for c in SCRIPT_THINGS]
    dagger += [float(table[c]["iou"]) for c in SCRIPT_STUFF]
    out = {
        "pq_mean": mean("pq", named),
        "pq_dagger": float(np.mean(dagger)),
        "sq_mean": mean("sq", named),
        "rq_mean": mean("rq", named),
        "iou_mean": float(miou),
        "pq_stuff": mean("pq", SCRIPT_STUFF),
        "rq_stuff": mean("rq", SCRIPT_STUFF),
        "sq_stuff": mean("sq", SCRIPT_STUFF),
        "pq_things": mean("pq", SCRIPT_THINGS),
        "rq_things": mean("rq", SCRIPT_THINGS),
        "sq_things": mean("sq", SCRIPT_THINGS),
    }
    for c in named:
        out[c] = {k: float(v) for k, v in table[c].items()}
    return out


def assert_same(ref: object, ours: PanopticCounts, summary: dict) -> None:
    """Equal counts, per-class scores and script scores."""
    np.testing.assert_array_equal(ours.tp, ref.pan_tp)
    np.testing.assert_array_equal(ours.fp, ref.pan_fp)
    np.testing.assert_array_equal(ours.fn, ref.pan_fn)
    np.testing.assert_array_equal(ours.confusion, ref.px_iou_conf_matrix)
    np.testing.assert_allclose(ours.iou_sum, ref.pan_iou, rtol=0, atol=TOL)
    _, _, _, pq, sq, rq = ref.getPQ()
    _, iou = ref.getSemIoU()
    per = ours.per_class()
    for key, theirs in (("pq", pq), ("sq", sq), ("rq", rq), ("iou", iou)):
        np.testing.assert_allclose(per[key], theirs, rtol=0, atol=TOL, err_msg=key)
    expected = script_scores(ref, config()[1])
    assert list(summary) == [*list(expected)[: len(SCORES_KEYS)], "classes"]
    assert list(summary["classes"]) == [n for n in config()[1] if n in expected]
    for key, value in expected.items():
        got = summary[key] if key in SCORES_KEYS else summary["classes"][key]
        assert got == pytest.approx(value, abs=TOL), key


def labels(raw: int, instance: int, n: int) -> np.ndarray:
    """`n` labels of one raw class and instance."""
    return np.full(n, (instance << 16) | raw, dtype=np.uint32)


def random_scan(rng: np.random.Generator, absent: frozenset[int] = frozenset()) -> Scan:
    """A scan of segments of every kind and a prediction that keeps, splits, merges, relabels,
    shrinks or misses each one, with noise, ignored points and predicted stuff instances."""
    lut = config()[0]
    gt_parts: list[np.ndarray] = []
    pred_parts: list[np.ndarray] = []
    pending_merge: dict[int, int] = {}
    things = [r for r in THING_RAW if lut[r] not in absent]
    stuff = [r for r in STUFF_RAW if lut[r] not in absent]
    sizes = [3, 10, 14, 15, 16, 49, 50, 51, 80, 200, 600]
    segments = [(int(rng.choice(things)), int(rng.integers(1, 400))) for _ in range(14)]
    segments += [(int(r), 0) for r in rng.choice(stuff, size=5, replace=False)]
    segments += [(int(rng.choice(stuff)), int(rng.integers(1, 5)))]
    for raw, instance in segments:
        n = int(rng.choice(sizes)) if instance else int(rng.integers(30, 900))
        gt = labels(raw, instance, n)
        pred_instance = int(rng.integers(0, 1 << 15)) if instance else 0
        pred = labels(raw, pred_instance, n)
        kind = rng.choice(["keep", "split", "merge", "swap", "shrink", "miss", "stuff-ids"])
        if kind == "split":
            cut = int(rng.integers(0, n + 1))
            pred[cut:] = (int(rng.integers(0, 1 << 15)) << 16) | raw
        elif kind == "merge":
            pred[:] = (pending_merge.setdefault(int(lut[raw]), pred_instance) << 16) | raw
        elif kind == "swap":
            pred[:] = (pred_instance << 16) | int(rng.choice(THING_RAW + STUFF_RAW))
        elif kind == "shrink":
            lost = rng.random(n) < rng.uniform(0.1, 0.7)
            pred[lost] = rng.choice(IGNORED_RAW + STUFF_RAW, size=int(lost.sum()))
        elif kind == "miss":
            pred[:] = int(rng.choice(IGNORED_RAW))
        elif kind == "stuff-ids":
            pred[:] = (rng.integers(0, 3, size=n).astype(np.uint32) << 16) | raw
        gt_parts.append(gt)
        pred_parts.append(pred)
    # Ignored ground truth, predicted as anything, and predicted segments lying on it.
    k = int(rng.integers(1, 300))
    gt_parts.append(rng.choice(IGNORED_RAW, size=k).astype(np.uint32))
    pred_parts.append(
        (rng.integers(0, 4, size=k).astype(np.uint32) << 16)
        | rng.choice(THING_RAW + STUFF_RAW + IGNORED_RAW, size=k).astype(np.uint32)
    )
    gt_parts.append(labels(0, 0, 60))
    pred_parts.append(labels(10, 77, 60))
    # Predicted segments of every size on no ground-truth segment of their class.
    for n in (14, 15, 49, 50, 120):
        gt_parts.append(labels(int(rng.choice(stuff)), 0, n))
        pred_parts.append(labels(int(rng.choice(things)), int(rng.integers(500, 600)), n))
    gt = np.concatenate(gt_parts)
    pred = np.concatenate(pred_parts)
    # Noise: a few points anywhere take another label.
    noisy = rng.random(gt.size) < 0.02
    pred[noisy] = rng.choice(pred, size=int(noisy.sum()))
    order = rng.permutation(gt.size)
    return pred[order], gt[order]


def scans(seed: int, count: int) -> Iterator[Scan]:
    """`count` random scans, each leaving out some classes."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        absent = frozenset(int(c) for c in rng.choice(np.arange(1, 20), size=4, replace=False))
        yield random_scan(rng, absent)


def he_example() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The toy problem of He et al. the reference's `__main__` scores (ignore, grass, sky, person,
    dog): predicted classes and instances, then ground-truth ones."""
    pred_sem = [0] * 50 + [1] * 40 + [2] * 10 + [2] * 40 + [1] * 10 + [3] * 50 + [3] * 300
    pred_inst = [0] * 150 + [35] * 50 + [8] * 200 + [95] * 100
    gt_sem = [0] * 50 + [1] * 50 + [2] * 50 + [4] * 50 + [3] * 300
    gt_inst = [0] * 150 + [22] * 50 + [33] * 150 + [42] * 50 + [11] * 100
    return tuple(np.array(a, dtype=np.int64) for a in (pred_sem, pred_inst, gt_sem, gt_inst))


def test_he_example_gives_the_pq_the_reference_prints(capsys: pytest.CaptureFixture) -> None:
    runpy.run_path(str(data_path("reference", "semantic_kitti_eval_np.py")), run_name="__main__")
    printed = capsys.readouterr().out
    totals = dict(re.findall(r"^(PQ|SQ|RQ|IoU): (\S+) True$", printed, flags=re.M))
    assert set(totals) == {"PQ", "SQ", "RQ", "IoU"}, printed
    per_class = {
        m[0]: [float(v) for v in m[1:]]
        for m in re.findall(
            r"^Class (\w+) \t PQ: (\S+) SQ: (\S+) RQ: (\S+) IoU: (\S+)$", printed, flags=re.M
        )
    }
    assert list(per_class) == ["ignore", "grass", "sky", "person", "dog"]

    ours = PanopticCounts(5, [0], [3, 4], KITTI_PANOPTIC, min_points=1)
    ours.add(*he_example())
    summary = ours.summary(list(per_class))
    assert summary["pq_mean"] == pytest.approx(0.47916666666666663, abs=TOL)
    assert summary["pq_mean"] == pytest.approx(float(totals["PQ"]), abs=TOL)
    assert summary["sq_mean"] == pytest.approx(float(totals["SQ"]), abs=TOL)
    assert summary["rq_mean"] == pytest.approx(float(totals["RQ"]), abs=TOL)
    assert summary["iou_mean"] == pytest.approx(float(totals["IoU"]), abs=TOL)
    per = ours.per_class()
    for c, (pq, sq, rq, iou) in enumerate(per_class.values()):
        got = [per[k][c] for k in ("pq", "sq", "rq", "iou")]
        assert got == pytest.approx([pq, sq, rq, iou], abs=TOL)

    ref = reference().PanopticEval(5, None, [0], min_points=1)
    ref.addBatch(*he_example())
    assert ref.getPQ()[0] == pytest.approx(0.47916666666666663, abs=TOL)
    np.testing.assert_array_equal(ours.tp, ref.pan_tp)
    np.testing.assert_array_equal(ours.fp, ref.pan_fp)
    np.testing.assert_array_equal(ours.fn, ref.pan_fn)


def test_random_scans_accumulated() -> None:
    assert_same(*run_both(list(scans(seed=1, count=6))))


@pytest.mark.parametrize("min_points", [1, 15, 51])
def test_other_minimum_sizes(min_points: int) -> None:
    assert_same(*run_both(list(scans(seed=min_points, count=3)), min_points=min_points))


def test_constructed_cases() -> None:
    car, moving_car, person, road, lane, vegetation = 10, 252, 30, 40, 60, 70
    cases: list[tuple[list[np.ndarray], list[np.ndarray]]] = [
        # Unmatched instances just below and at the minimum size, both sides.
        ([labels(road, 0, 49), labels(road, 0, 50)], [labels(car, 1, 49), labels(car, 2, 50)]),
        ([labels(car, 1, 49), labels(car, 2, 50)], [labels(road, 0, 49), labels(road, 0, 50)]),
        # A matched instance far below the minimum counts.
        ([labels(person, 3, 5)], [labels(person, 9, 5)]),
        # A half-and-half split is no match (IoU 0.5 is not above 0.5).
        ([labels(car, 1, 60), labels(car, 2, 60)], [labels(car, 7, 120)]),
        # A 61/59 split matches the larger part; merged instances match the larger one.
        ([labels(car, 1, 61), labels(car, 2, 59)], [labels(car, 7, 120)]),
        ([labels(car, 4, 70), labels(car, 4, 50)], [labels(car, 1, 70), labels(car, 2, 50)]),
        # car and moving-car of one instance are two segments, as are road and lane-marking.
        ([labels(car, 5, 100)], [labels(car, 5, 60), labels(moving_car, 5, 40)]),
        ([labels(road, 0, 300)], [labels(road, 0, 200), labels(lane, 0, 100)]),
        # Predicted stuff with instance ids is as many segments.
        ([labels(vegetation, 1, 200), labels(vegetation, 2, 100)], [labels(vegetation, 0, 300)]),
        # A class swap, and everything ignored.
        ([labels(person, 1, 80)], [labels(car, 1, 80)]),
        ([labels(car, 1, 80)], [labels(0, 0, 40), labels(52, 0, 40)]),
        # No points at all.
        ([np.zeros(0, dtype=np.uint32)], [np.zeros(0, dtype=np.uint32)]),
    ]
    all_scans = []
    for pred, gt in cases:
        scan = (np.concatenate(pred), np.concatenate(gt))
        assert_same(*run_both([scan]))
        all_scans.append(scan)
    assert_same(*run_both(all_scans))


def test_the_real_scan(real_label_path) -> None:
    gt = np.fromfile(real_label_path, dtype=np.uint32)
    rng = np.random.default_rng(5)
    pred = gt.copy()
    # Renumber the instances, relabel a tenth of the points and split one instance in two.
    pred = ((pred >> 16) * np.uint32(3) << 16) | (pred & 0xFFFF)
    flip = rng.random(gt.size) < 0.1
    pred[flip] = rng.choice(gt, size=int(flip.sum()))
    things = np.flatnonzero((gt >> 16) > 0)
    pred[things[: things.size // 3]] |= np.uint32(1 << 30)
    ref, ours, summary = run_both([(pred, gt), (gt, gt)])
    assert_same(ref, ours, summary)
    assert ours.tp.sum() > 10


def test_counts_merge_to_the_whole() -> None:
    all_scans = list(scans(seed=11, count=4))
    _, whole, _ = run_both(all_scans)
    _, first, _ = run_both(all_scans[:1])
    _, rest, _ = run_both(all_scans[1:])
    first.merge(rest)
    for key in ("tp", "fp", "fn", "confusion"):
        np.testing.assert_array_equal(getattr(first, key), getattr(whole, key))
    np.testing.assert_allclose(first.iou_sum, whole.iou_sum, rtol=0, atol=TOL)
    assert first.num_scans == 4
    names = config()[1]
    merged, expected = first.summary(names), whole.summary(names)
    assert list(merged) == list(expected)
    for key, value in expected.items():
        if key == "classes":
            for name, scores in value.items():
                assert merged[key][name] == pytest.approx(scores, abs=TOL), name
        else:
            assert merged[key] == pytest.approx(value, abs=TOL), key
    other = PanopticCounts.for_classes(names, [0], KITTI_PANOPTIC, min_points=10)
    with pytest.raises(ValueError, match="same classes and rules"):
        first.merge(other)


def test_summary_keys_and_things() -> None:
    _, names, ignore = config()
    assert list(KITTI_PANOPTIC.thing_names) == SCRIPT_THINGS
    counts = PanopticCounts.for_classes(names, ignore, KITTI_PANOPTIC)
    assert [names[c] for c in counts.things] == sorted(SCRIPT_THINGS, key=names.index)
    assert sorted(names[c] for c in counts.stuff) == sorted(SCRIPT_STUFF)
    assert counts.min_points == 50
    summary = counts.summary(names)
    assert list(summary)[:11] == SCORES_KEYS
    assert list(summary)[11:] == ["classes"]
    assert list(summary["classes"]) == names[1:]
    assert all(list(summary["classes"][n]) == ["pq", "sq", "rq", "iou"] for n in names[1:])
    # Nothing counted: every score is 0 (the evaluators' eps), none NaN.
    assert all(summary[k] == 0.0 for k in SCORES_KEYS)


def test_refuses_what_the_official_evaluator_cannot_count() -> None:
    counts = PanopticCounts(3, [0], [1], KITTI_PANOPTIC)
    ok = np.array([1, 2])
    with pytest.raises(ValueError, match=r"0\.\.2"):
        counts.add(np.array([1, 3]), ok, ok, ok)
    with pytest.raises(ValueError, match="differ"):
        counts.add(ok, ok, ok, np.array([1]))
    with pytest.raises(ValueError, match="integers"):
        counts.add(ok, ok.astype(float), ok, ok)
    with pytest.raises(ValueError, match="ground-truth instances"):
        counts.add(ok, ok, ok, np.array([1, 2**31 - 1]))
    with pytest.raises(ValueError, match="predicted instances"):
        counts.add(ok, np.array([-1, 0]), ok, ok)
    # The largest ids the official offset arithmetic keeps apart count alike on both sides.
    ref = reference().PanopticEval(3, None, [0], min_points=1)
    ours = PanopticCounts(3, [0], [1], KITTI_PANOPTIC, min_points=1)
    cls = np.array([1, 1, 1, 2, 2])
    pred_ids = np.array([2**32 - 2, 2**32 - 2, 0, 2**32 - 3, 5])
    gt_ids = np.array([2**31 - 2, 2**31 - 2, 2**31 - 2, 0, 2**31 - 3])
    ref.addBatch(cls, pred_ids, cls, gt_ids)
    ours.add(cls, pred_ids, cls, gt_ids)
    for mine, theirs in ((ours.tp, ref.pan_tp), (ours.fp, ref.pan_fp), (ours.fn, ref.pan_fn)):
        np.testing.assert_array_equal(mine, theirs)
    np.testing.assert_allclose(ours.iou_sum, ref.pan_iou, rtol=0, atol=TOL)
    with pytest.raises(ValueError, match="cannot be ignored"):
        PanopticCounts(3, [0], [0], KITTI_PANOPTIC)
    with pytest.raises(ValueError, match="things missing"):
        PanopticCounts.for_classes(["a", "car"], [0], KITTI_PANOPTIC)
