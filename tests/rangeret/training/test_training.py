"""Training: augmentations and mixes, the losses against hand-computed values and their
definitions, schedules, exact resume, `run_train` end to end, training on other dataset profiles
(PandaSet, SemanticPOSS), the Ray Train path, and over-fitting the real scan."""

from __future__ import annotations

import argparse
import io
import itertools
import logging
import math
import time
import warnings
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn.parallel import DistributedDataParallel

from rangeret.cli.train import add_train_arguments, run_train
from rangeret.dataset.labels import parse_label_config, semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover, labels_dir, velodyne_dir
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.projection import CHANNEL_MEANS, CHANNEL_STDS, ProjectionConfig
from rangeret.inference.predictor import Predictor
from rangeret.inference.runtime.precision import auto_choice
from rangeret.io.scans import KITTI_RECORD, read_scan
from rangeret.models import CheckpointError, build_model, load_checkpoint
from rangeret.sim import SensorConfig, simulate_dataset
from rangeret.train_options import config_from_args
from rangeret.training import TrainConfig, Trainer
from rangeret.training.augment import (
    JITTER_RATE,
    augment_points,
    global_rotation,
    random_flip,
    random_jitter,
    random_scale,
)
from rangeret.training.config import parse_override
from rangeret.training.data import (
    EpochSampler,
    RangeDataset,
    collate,
    find_scans,
    steps_per_epoch,
)
from rangeret.training.distributed import ddp_find_unused, unused_parameters
from rangeret.training.logs import CsvLog
from rangeret.training.losses import (
    SegmentationLoss,
    class_weights,
    focal_loss,
    lovasz_softmax,
    weighted_cross_entropy,
)
from rangeret.training.range_mixes import (
    MIXES,
    MixSettings,
    RangeImage,
    range_mix,
    range_paste,
    range_shift,
    range_union,
    rare_classes,
)
from rangeret.training.schedule import build_optimizer, build_scheduler
from rangeret.training.state import STATE
from tests.support.paths import data_path

SMALL = {"height": 16, "width": 256}
#: A one-block thesis network, for tests of the training step rather than of what it learns.
TINY_NET = (("layers", 1), ("dim", 16), ("heads", 2))


@pytest.fixture(autouse=True)
def one_thread():
    """Every test here on one torch thread: when other processes keep the two cores busy, torch's
    spinning worker threads can stall each step many times over; one thread keeps times steady."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def sim_root(tmp_path_factory) -> Path:
    """A tiny simulated tree: 4 training scans in 00, 2 validation scans in 08 (16 x 256 sensor)."""
    root = tmp_path_factory.mktemp("sim")
    simulate_dataset(
        root,
        {"00": 4, "08": 2},
        sensor=SensorConfig(beams=16, azimuth_steps=256),
        seed=3,
        profile=load_profile("semantickitti"),
    )
    return root


@pytest.fixture(scope="module")
def sim_scans(sim_root):
    return discover(sim_root, ["00", "08"], with_labels=True, layout=KITTI_LAYOUT).scans


def small_config(root: Path, out: Path, **changes) -> TrainConfig:
    values = {
        "dataset": str(root),
        "out": str(out),
        "train_sequences": ("00",),
        "val_sequences": ("08",),
        "epochs": 2,
        "loader_workers": 0,
        "progress": False,
        "device": "cpu",
        **SMALL,
        **changes,
    }
    return TrainConfig(**values)


# Point augmentations ---------------------------------------------------------------------------


def test_each_point_augmentation_does_what_algorithm_2_says():
    rng = np.random.default_rng(0)
    xy = rng.normal(0, 20, (500, 2))
    norms = np.linalg.norm(xy, axis=1)
    for seed in range(20):
        scaled = random_scale(xy, np.random.default_rng(seed))
        factor = scaled / xy
        assert np.allclose(factor, factor[0, 0]) and 0.95 <= factor[0, 0] <= 1.05
        rotated = global_rotation(xy, np.random.default_rng(seed))
        assert np.allclose(np.linalg.norm(rotated, axis=1), norms)
        shift = random_jitter(xy, np.random.default_rng(seed)) - xy
        assert np.allclose(shift, shift[0]) and np.all(np.abs(shift[0]) <= JITTER_RATE)
    flips = {
        tuple(np.sign(random_flip(xy[:1], np.random.default_rng(s))[0] / xy[0])) for s in range(40)
    }
    assert flips == {(1, 1), (-1, 1), (1, -1), (-1, -1)}


def test_augment_points_moves_only_x_and_y_of_real_points():
    rng = np.random.default_rng(1)
    points = rng.normal(0, 15, (2000, 4)).astype(np.float32)
    points[5, :3] = 0
    out = augment_points(points, np.random.default_rng(7))
    assert out.shape == points.shape and out.dtype == points.dtype
    assert np.array_equal(out[:, 2:], points[:, 2:])
    assert np.array_equal(out[5], points[5])
    keep = np.ones(len(points), bool)
    keep[5] = False
    # x, y undergo one similarity transform: scale * rotation (possibly mirrored) plus a shift.
    src = np.column_stack([points[keep, :2], np.ones(keep.sum())]).astype(np.float64)
    fit, *_ = np.linalg.lstsq(src, out[keep, :2].astype(np.float64), rcond=None)
    assert np.abs(src @ fit - out[keep, :2]).max() < 1e-3
    singular = np.linalg.svd(fit[:2])[1]
    assert np.allclose(singular, singular[0], atol=1e-5) and 0.95 <= singular[0] <= 1.05
    assert np.all(np.abs(fit[2]) <= JITTER_RATE * 1.06)
    assert not np.allclose(out[keep, :2], points[keep, :2])


def test_dataset_labels_move_with_their_points(sim_scans):
    config = semantickitti()
    projection = ProjectionConfig(**SMALL)
    plain = RangeDataset(sim_scans, projection, config, with_points=True, points=KITTI_RECORD)
    moved = RangeDataset(
        sim_scans, projection, config, augment=True, with_points=True, seed=5, points=KITTI_RECORD
    )
    for index in range(3):
        points, classes = plain.points_and_classes(index)
        before, after = plain[index], moved[(2, index)]
        assert len(after["point_labels"]) == len(points) == len(before["point_labels"])
        assert np.array_equal(after["point_labels"], classes)
        assert not np.array_equal(after["label"], before["label"])
        # Where a point wins its pixel, the pixel holds its class, its own z and its own range.
        px, py = after["proj_x"], after["proj_y"]
        valid = px >= 0
        assert valid.sum() == (points[:, :3] != 0).any(axis=1).sum()
        winner = valid.copy()
        winner[valid] = after["unproj_range"][valid] == after["proj_range"][py[valid], px[valid]]
        pixel_labels = after["label"][py[winner], px[winner]]
        assert np.mean(pixel_labels == classes[winner]) > 0.999
        z = after["image"][3] * CHANNEL_STDS[3] + CHANNEL_MEANS[3]
        assert np.allclose(z[py[winner], px[winner]], points[winner, 2], atol=1e-4)
        assert np.array_equal(after["mask"], after["proj_range"] >= 0)
        assert np.all(after["label"][~after["mask"]] == 0)
    again = moved[(2, 0)]
    assert np.array_equal(again["image"], moved[(2, 0)]["image"])
    assert not np.array_equal(again["image"], moved[(3, 0)]["image"])


# Range-image mixes ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def two_images(sim_scans):
    ds = RangeDataset(sim_scans, ProjectionConfig(**SMALL), semantickitti(), points=KITTI_RECORD)
    images = []
    for i in (0, 4):
        s = ds[i]
        images.append(RangeImage(s["image"], s["label"], s["mask"]))
    return images


def assert_pixels_from(result: RangeImage, sources: list[RangeImage]) -> np.ndarray:
    """Every pixel of `result` is the same pixel of one source; returns which source (H, W)."""
    assert result.image.shape == sources[0].image.shape and result.image.dtype == np.float32
    assert result.label.shape == sources[0].label.shape and result.label.dtype == np.int64
    assert result.mask.shape == sources[0].mask.shape and result.mask.dtype == bool
    origin = np.full(result.label.shape, -1)
    for k, src in reversed(list(enumerate(sources))):
        same = (
            (result.image == src.image).all(0)
            & (result.label == src.label)
            & (result.mask == src.mask)
        )
        origin[same] = k
    assert (origin >= 0).all()
    assert np.all(result.label[~result.mask] == 0)
    return origin


def strip_layouts(h: int, w: int):
    """Every pixel set RangeMix may take from the second scan: odd strips of rows, of columns, or
    the odd cells of their checkerboard, for 2 to 6 strips."""
    for k in range(2, 7):
        rows = (np.arange(h) * k // h % 2 == 1)[:, None]
        cols = (np.arange(w) * k // w % 2 == 1)[None, :]
        yield np.broadcast_to(rows, (h, w))
        yield np.broadcast_to(cols, (h, w))
        yield rows ^ cols


def test_range_mix_swaps_whole_strips(two_images):
    a, b = two_images
    differs = (a.image != b.image).any(0) | (a.label != b.label) | (a.mask != b.mask)
    for seed in range(8):
        origin = assert_pixels_from(range_mix(a, b, np.random.default_rng(seed)), [a, b])
        taken = origin == 1
        assert taken[differs].any() and not taken[differs].all()
        assert any(
            np.array_equal(taken[differs], layout[differs]) for layout in strip_layouts(16, 256)
        )


def test_range_union_fills_half_of_the_empty_pixels(two_images):
    a, b = two_images
    out = range_union(a, b, np.random.default_rng(0))
    assert_pixels_from(out, [a, b])
    changed = (out.image != a.image).any(0)
    candidates = ~a.mask & b.mask
    assert not (changed & ~candidates).any()
    assert 0.35 < changed.sum() / candidates.sum() < 0.65
    assert np.array_equal(out.label[a.mask], a.label[a.mask])


def test_range_paste_copies_the_chosen_classes(two_images):
    a, b = two_images
    present = [int(c) for c in np.unique(b.label) if c]
    chosen = present[:2]
    out = range_paste(a, b, chosen)
    assert_pixels_from(out, [a, b])
    pasted = np.isin(b.label, chosen) & b.mask
    assert np.array_equal(out.label[pasted], b.label[pasted])
    assert np.array_equal(out.label[~pasted], a.label[~pasted])
    freq = semantickitti().class_frequencies()
    rare = rare_classes(freq, semantickitti().ignored)
    assert 0 not in rare and {2, 3, 6, 7, 8} <= set(rare) and 9 not in rare


def test_range_shift_rolls_the_azimuth(two_images):
    a, _ = two_images
    w = a.label.shape[1]
    out = range_shift(a, np.random.default_rng(4))
    shifts = [
        k
        for k in range(w)
        if np.array_equal(np.roll(a.label, k, axis=1), out.label)
        and np.array_equal(np.roll(a.image, k, axis=-1), out.image)
    ]
    assert shifts and any(w // 4 <= k < 3 * w // 4 for k in shifts)
    assert np.array_equal(np.roll(a.mask, shifts[0], axis=1), out.mask)


def test_mix_settings_apply_each_mix_with_its_probability(two_images):
    a, b = two_images
    loads = []

    def partner():
        loads.append(1)
        return b

    unchanged = MixSettings(MIXES, probability=0.0).apply(a, partner, np.random.default_rng(0))
    assert unchanged is a and not loads
    mixed = MixSettings(MIXES, probability=1.0, paste_classes=(9, 11)).apply(
        a, partner, np.random.default_rng(0)
    )
    assert len(loads) == 1
    assert mixed.image.shape == a.image.shape and mixed.label.shape == a.label.shape
    assert np.all(mixed.label[~mixed.mask] == 0)
    with pytest.raises(ValueError, match="unknown mixes"):
        MixSettings(("cutmix",))


def test_dataset_with_mixes_is_reproducible(sim_scans):
    settings = MixSettings(MIXES, probability=1.0, paste_classes=(1, 9))
    ds = RangeDataset(
        sim_scans,
        ProjectionConfig(**SMALL),
        semantickitti(),
        augment=True,
        mixing=settings,
        points=KITTI_RECORD,
    )
    first, second = ds[(1, 2)], ds[(1, 2)]
    for key in ("image", "label", "mask"):
        assert np.array_equal(first[key], second[key])
    assert np.all(first["label"][~first["mask"]] == 0)
    batch = collate([ds[(0, 0)], ds[(0, 1)]])
    assert batch["image"].shape == (2, 5, 16, 256) and batch["label"].dtype == torch.int64


def test_epoch_sampler_deals_equal_shares_and_skips_done_batches():
    shares = [
        EpochSampler(10, 3, 0, batch_size=2, rank=r, world_size=3).indices() for r in range(3)
    ]
    assert all(len(s) == 4 for s in shares)
    assert set(itertools.chain(*shares)) == set(range(10))
    assert EpochSampler(10, 3, 0).indices() != EpochSampler(10, 4, 0).indices()
    resumed = list(EpochSampler(10, 3, 0, batch_size=2, start=2))
    assert [i for _, i in resumed] == EpochSampler(10, 3, 0).indices()[4:]
    assert steps_per_epoch(10, 2, 3) == 2
    assert EpochSampler(5, 0, 0, rank=1, world_size=2, shuffle=False, pad=False).indices() == [1, 3]


# Losses --------------------------------------------------------------------------------------


def test_class_weights_from_frequencies():
    freq = np.array([0.1, 0.5, 0.01])
    ignored = [True, False, False]
    w = class_weights(freq, ignored)
    assert w[0] == 0 and math.isclose(w[1], 1 / math.sqrt(0.501), rel_tol=1e-6)
    assert math.isclose(w[2], 1 / math.sqrt(0.011), rel_tol=1e-6)
    assert math.isclose(class_weights(freq, ignored, "inverse")[2], 1 / 0.011, rel_tol=1e-6)
    assert class_weights(freq, ignored, "none").tolist() == [0, 1, 1]
    with pytest.raises(ValueError):
        class_weights(freq, ignored, "log")


def hand_case():
    """Three pixels in a 1 x 3 image over 3 classes: labels 1, 2 and the ignored 0."""
    logits = torch.tensor([[0.0, 0.0, 0.0], [0.0, math.log(2.0), 0.0], [5.0, -3.0, 2.0]])
    return logits.T.reshape(1, 3, 1, 3), torch.tensor([[[1, 2, 0]]])


def test_weighted_cross_entropy_by_hand():
    logits, labels = hand_case()
    # Pixel 1: softmax (1/3, 1/3, 1/3) -> -log(1/3); pixel 2: p = 1/4 for class 2 -> -log(1/4).
    weights = torch.tensor([0.0, 1.0, 3.0])
    expected = (1 * math.log(3) + 3 * math.log(4)) / 4
    assert math.isclose(
        float(weighted_cross_entropy(logits, labels, weights)), expected, rel_tol=1e-6
    )


def test_focal_loss_by_hand():
    logits, labels = hand_case()
    alpha = torch.tensor([0.0, 0.5, 1.0])
    expected = (0.5 * (2 / 3) ** 2 * math.log(3) + 1.0 * (3 / 4) ** 2 * math.log(4)) / 2
    assert math.isclose(float(focal_loss(logits, labels, alpha, gamma=2.0)), expected, rel_tol=1e-6)
    # gamma 0 and alpha 1 is the plain cross-entropy.
    plain = (math.log(3) + math.log(4)) / 2
    assert math.isclose(
        float(focal_loss(logits, labels, torch.ones(3), gamma=0.0)), plain, rel_tol=1e-6
    )


def test_lovasz_softmax_by_hand():
    probs = torch.tensor([[0.0, 0.9, 0.1], [0.0, 0.4, 0.6], [0.0, 0.3, 0.7], [0.5, 0.2, 0.3]])
    labels = torch.tensor([1, 1, 2, 0])
    # Class 1: errors (0.1, 0.6, 0.3), truth (1, 1, 0); sorted 0.6 (fg), 0.3 (bg), 0.1 (fg):
    # Delta_J of the prefixes 1/2, 2/3, 3/3 -> g = (1/2, 1/6, 1/3) -> 0.3 + 0.05 + 0.1/3.
    # Class 2: errors (0.1, 0.6, 0.3), truth (0, 0, 1); sorted 0.6 (bg), 0.3 (fg), 0.1 (bg):
    # Delta_J 1/2, 2/2, 3/3 -> g = (1/2, 1/2, 0) -> 0.3 + 0.15. The last pixel is ignored.
    expected = ((0.3 + 0.05 + 0.1 / 3) + 0.45) / 2
    assert math.isclose(float(lovasz_softmax(probs, labels)), expected, rel_tol=1e-6)


def jaccard_loss(mispredicted: set[int], truth: set[int]) -> Fraction:
    """Delta_J(M) = |M| / |truth union M| (the Jaccard loss of a set of mispredicted pixels)."""
    union = truth | mispredicted
    return Fraction(len(mispredicted), len(union)) if union else Fraction(0)


def lovasz_extension_greedy(errors: list[Fraction], truth: set[int]) -> Fraction:
    """sum_i m_pi(i) (Delta(first i) - Delta(first i - 1)), errors sorted in decreasing order."""
    order = sorted(range(len(errors)), key=lambda i: -errors[i])
    total, previous = Fraction(0), Fraction(0)
    for i in range(1, len(order) + 1):
        current = jaccard_loss(set(order[:i]), truth)
        total += errors[order[i - 1]] * (current - previous)
        previous = current
    return total


def lovasz_extension_integral(errors: list[Fraction], truth: set[int]) -> Fraction:
    """The same extension as the integral over t in [0, 1] of Delta({i : m_i >= t})."""
    levels = sorted(set(errors) | {Fraction(0)})
    total = Fraction(0)
    for low, high in itertools.pairwise(levels):
        total += (high - low) * jaccard_loss({i for i, m in enumerate(errors) if m >= high}, truth)
    return total


def lovasz_by_definition(probs: np.ndarray, labels: np.ndarray, ignore: int = 0) -> float:
    """Eq. 4.5-4.7 literally, in exact arithmetic, over the classes present among labelled pixels."""
    keep = [i for i in range(len(labels)) if labels[i] != ignore]
    present = sorted({int(labels[i]) for i in keep})
    losses = []
    for c in present:
        truth = {j for j, i in enumerate(keep) if labels[i] == c}
        errors = [Fraction(float(1 - probs[i, c] if labels[i] == c else probs[i, c])) for i in keep]
        greedy = lovasz_extension_greedy(errors, truth)
        assert greedy == lovasz_extension_integral(errors, truth)
        losses.append(greedy)
    return float(sum(losses) / len(losses))


def test_lovasz_softmax_equals_its_definition_on_random_inputs():
    gen = torch.Generator().manual_seed(0)
    for trial in range(25):
        pixels, classes = 4 + trial % 9, 2 + trial % 4
        logits = torch.randn(pixels, classes, generator=gen, dtype=torch.float64) * 2
        labels = torch.randint(0, classes, (pixels,), generator=gen)
        labels[0] = 1
        probs = logits.softmax(dim=1)
        ours = float(lovasz_softmax(probs, labels))
        assert math.isclose(
            ours, lovasz_by_definition(probs.numpy(), labels.numpy()), rel_tol=1e-9, abs_tol=1e-12
        )
    image = torch.randn(2, 4, 3, 5, generator=gen, dtype=torch.float64).softmax(dim=1)
    target = torch.randint(0, 4, (2, 3, 5), generator=gen)
    flat = lovasz_by_definition(
        image.permute(0, 2, 3, 1).reshape(-1, 4).numpy(), target.reshape(-1).numpy()
    )
    assert math.isclose(float(lovasz_softmax(image, target)), flat, rel_tol=1e-9)


def test_segmentation_loss_sums_its_terms_and_ignores_class_0():
    gen = torch.Generator().manual_seed(1)
    logits = torch.randn(2, 5, 4, 6, generator=gen, requires_grad=True)
    labels = torch.randint(0, 5, (2, 4, 6), generator=gen)
    weights = class_weights([0.2, 0.4, 0.2, 0.1, 0.1], [True, False, False, False, False])
    loss = SegmentationLoss(("ce", "lovasz", "focal"), weights)
    total, terms = loss(logits, labels)
    assert set(terms) == {"ce", "lovasz", "focal"}
    assert math.isclose(float(total.detach()), float(sum(terms.values()).detach()), rel_tol=1e-6)
    total.backward()
    assert torch.isfinite(logits.grad).all()
    assert torch.all(logits.grad.permute(0, 2, 3, 1)[labels == 0] == 0)
    changed = logits.detach().clone()
    changed.permute(0, 2, 3, 1)[labels == 0] += 10
    assert math.isclose(float(loss(changed, labels)[0]), float(total.detach()), rel_tol=1e-6)
    only = SegmentationLoss(("lovasz",), weights)
    assert set(only(logits, labels)[1]) == {"lovasz"}
    nothing = loss(logits, torch.zeros_like(labels))[0]
    assert float(nothing.detach()) == 0.0


# Optimiser and schedules ---------------------------------------------------------------------


def test_onecycle_and_cosine_schedules():
    for kind in ("onecycle", "cosine"):
        p = torch.nn.Parameter(torch.zeros(3))
        opt = build_optimizer([p], lr=1e-3, weight_decay=0.05)
        sched = build_scheduler(opt, kind, total_steps=100, max_lr=1e-2, warmup=0.3)
        lrs = []
        for _ in range(100):
            lrs.append(opt.param_groups[0]["lr"])
            opt.step()
            sched.step()
        assert math.isclose(lrs[0], 1e-3, rel_tol=1e-6)
        assert 28 <= int(np.argmax(lrs)) <= 30 and math.isclose(max(lrs), 1e-2, rel_tol=1e-2)
        assert lrs[-1] < 1e-4
        assert opt.param_groups[0]["weight_decay"] == 0.05
        if kind == "onecycle":
            assert math.isclose(opt.param_groups[0]["betas"][0], 0.95, rel_tol=1e-3)
        buffer = io.BytesIO()
        torch.save(sched.state_dict(), buffer)
        buffer.seek(0)
        restored = build_scheduler(
            build_optimizer([p]), kind, total_steps=100, max_lr=1e-2, warmup=0.3
        )
        restored.load_state_dict(torch.load(buffer, weights_only=True))
        assert restored.last_epoch == 100
    assert all(a <= b for a, b in itertools.pairwise(lrs[:30]))
    for total in (1, 2, 3, 10):
        opt = build_optimizer([torch.nn.Parameter(torch.zeros(1))])
        sched = build_scheduler(opt, "onecycle", total_steps=total, max_lr=1e-2, warmup=0.1)
        for _ in range(total):
            assert 0 < opt.param_groups[0]["lr"] <= 1e-2
            opt.step()
            sched.step()


# Models under data parallelism ---------------------------------------------------------------


def test_unused_parameters_are_the_released_networks_gate():
    assert unused_parameters(build_model("rangeret-thesis", **SMALL)) == []
    cir = build_model("rangeret-cir", **SMALL)
    assert unused_parameters(cir) == [f"backbone.retentions.{i}.g_proj.weight" for i in range(8)]
    assert all(p.grad is None for p in cir.parameters())


def test_ddp_looks_for_unused_parameters_only_for_the_released_network(caplog):
    caplog.set_level(logging.INFO, logger="rangeret.training")
    assert ddp_find_unused(build_model("rangeret-thesis", **SMALL)) is False
    assert "without find_unused_parameters" in caplog.text
    caplog.clear()
    assert ddp_find_unused(build_model("rangeret-cir", **SMALL)) is True
    assert all(f"backbone.retentions.{i}.g_proj.weight" in caplog.text for i in range(8))


@pytest.mark.slow
def test_ddp_in_a_one_process_group_runs_with_the_decided_flag(tmp_path):
    """Two steps under DDP (gloo, one process) with `ddp_find_unused`'s flag work for both
    networks; the released one fails without it, so the flag is needed there."""
    dist = torch.distributed
    dist.init_process_group(
        "gloo", init_method=f"file://{tmp_path / 'group'}", rank=0, world_size=1
    )
    x = torch.randn(1, 5, *SMALL.values(), generator=torch.Generator().manual_seed(0))

    def two_steps(model: torch.nn.Module, find_unused: bool) -> None:
        network = DistributedDataParallel(model, find_unused_parameters=find_unused)
        for _ in range(2):
            network(x).square().mean().backward()

    try:
        for name in ("rangeret-thesis", "rangeret-cir"):
            model = build_model(name, **SMALL, **dict(TINY_NET))
            two_steps(model, ddp_find_unused(model))
        with pytest.raises(RuntimeError, match="finished reduction in the prior iteration"):
            two_steps(build_model("rangeret-cir", **SMALL, **dict(TINY_NET)), False)
    finally:
        dist.destroy_process_group()


def test_train_config_round_trip_and_overrides():
    config = TrainConfig(
        dataset="d",
        out="o",
        model_overrides=(("decay", "manhattan"), ("patch_size", (4, 4))),
        mixes=("rangemix",),
        val_sequences=(),
    )
    assert TrainConfig.from_dict(config.to_dict()) == config
    assert parse_override("patch_size=4x4") == ("patch_size", (4, 4))
    assert parse_override("residual=false") == ("residual", False)
    assert parse_override("layers=2") == ("layers", 2)
    with pytest.raises(ValueError):
        parse_override("depth=3")
    with pytest.raises(ValueError):
        TrainConfig(dataset="d", out="o", losses=("dice",))


# Training runs -------------------------------------------------------------------------------


def test_resume_continues_exactly(sim_root, tmp_path):
    """6 steps, then a resumed run to 12, against 12 steps straight: same losses and weights."""
    changes = {"epochs": 3, "mixes": MIXES, "mix_probability": 0.5}
    straight = Trainer(small_config(sim_root, tmp_path / "straight", **changes)).fit()
    first = Trainer(small_config(sim_root, tmp_path / "split", **changes))
    partial = first.fit(until_step=6)
    assert [r["step"] for r in partial.steps] == list(range(1, 7))
    state = torch.load(tmp_path / "split" / STATE, weights_only=True)
    assert state["step"] == 6 and state["epoch_totals"]["batches"] == 2
    resumed = Trainer(small_config(sim_root, tmp_path / "split", resume=True, **changes)).fit()
    assert [r["step"] for r in resumed.steps] == list(range(7, 13))
    for a, b in zip(straight.steps[6:], resumed.steps, strict=True):
        assert abs(a["loss"] - b["loss"]) <= 1e-6 and a["lr"] == b["lr"]
    a = load_checkpoint(tmp_path / "straight" / "last.pt").state_dict()
    b = load_checkpoint(tmp_path / "split" / "last.pt").state_dict()
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    straight_rows = (tmp_path / "straight" / "steps.csv").read_text().splitlines()
    split_rows = (tmp_path / "split" / "steps.csv").read_text().splitlines()
    assert len(split_rows) == 13
    assert [r.split(",")[:2] for r in split_rows] == [r.split(",")[:2] for r in straight_rows]
    split_epochs = CsvLog(tmp_path / "split" / "metrics.csv", []).read()
    straight_epochs = CsvLog(tmp_path / "straight" / "metrics.csv", []).read()
    assert len(split_epochs) == len(straight_epochs) == 3
    for a, b in zip(split_epochs, straight_epochs, strict=True):
        for key in ("step", "train_loss", "train_miou_image", "val_loss", "val_miou_knn"):
            assert math.isclose(float(a[key]), float(b[key]), rel_tol=1e-6, abs_tol=1e-9)

    with pytest.raises(ValueError, match="already holds a training run"):
        Trainer(small_config(sim_root, tmp_path / "split", **changes))
    with pytest.raises(ValueError, match="lr"):
        Trainer(small_config(sim_root, tmp_path / "split", resume=True, lr=2e-3, **changes))
    with pytest.raises(FileNotFoundError):
        Trainer(small_config(sim_root, tmp_path / "none", resume=True))


def test_run_train_end_to_end(sim_root, tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    out = tmp_path / "run"
    argv = [
        "--dataset",
        str(sim_root),
        "--model",
        "rangeret-thesis",
        "--out",
        str(out),
        "--epochs",
        "2",
        "--height",
        "16",
        "--width",
        "256",
        "--train-sequences",
        "00",
        "--val-sequences",
        "08",
        "--loader-workers",
        "0",
        "--mixes",
        "rangemix",
        "rangeshift",
        "--override",
        "layers=2",
        "--device",
        "cpu",
    ]
    args = parser.parse_args(argv)
    args.quiet = True
    assert run_train(args) == 0
    for name in ("last.pt", "best.pt", "last.state.pt", "metrics.csv", "steps.csv", "curves.png"):
        assert (out / name).is_file()
    assert (out / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "best checkpoint" in capsys.readouterr().out

    model = load_checkpoint(out / "last.pt")
    info = model.checkpoint_info
    assert info.name == "rangeret-thesis" and info.config["layers"] == 2
    assert (info.config["height"], info.config["width"]) == (16, 256)
    meta = info.metadata
    assert meta["epoch"] == 2 and meta["step"] == 8 and meta["epoch_complete"]
    assert meta["optimizer"]["name"] == "AdamW" and meta["scheduler"]["name"] == "OneCycleLR"
    assert meta["losses"] == ["ce", "lovasz", "focal"]
    assert {"val_miou_image", "val_miou_points", "val_miou_knn", "train_loss"} <= set(
        meta["metrics"]
    )
    assert parse_label_config(info.label_config, "checkpoint") == semantickitti()
    assert ProjectionConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in info.projection.items()}
    ) == ProjectionConfig(**SMALL)
    best = load_checkpoint(out / "best.pt").checkpoint_info.metadata["best"]
    assert best["metric"] == "val_miou_knn" and best["epoch"] in (1, 2)
    rows = (out / "metrics.csv").read_text().splitlines()
    assert len(rows) == 3 and "val_miou_knn" in rows[0]
    assert len((out / "steps.csv").read_text().splitlines()) == 9

    with pytest.raises(ValueError, match="already holds"):
        run_train(args)
    args.resume = True
    assert run_train(args) == 0
    assert len((out / "steps.csv").read_text().splitlines()) == 9


def test_missing_labels_are_reported(tmp_path):
    root = tmp_path / "data"
    simulate_dataset(
        root,
        {"00": 2},
        sensor=SensorConfig(beams=8, azimuth_steps=64),
        profile=load_profile("semantickitti"),
    )
    (labels_dir(root, "00", layout=KITTI_LAYOUT) / "000001.label").unlink()
    assert (velodyne_dir(root, "00", layout=KITTI_LAYOUT) / "000001.bin").exists()
    with pytest.raises(ValueError, match=r"000001\.label is missing"):
        Trainer(small_config(root, tmp_path / "out", val_sequences=()))


# Precision and host synchronisation ------------------------------------------------------------

#: Host read-backs of a tensor: each waits for the device (and `.cpu()` copies it back).
HOST_READS = (
    "item",
    "tolist",
    "cpu",
    "numpy",
    "__array__",
    "__float__",
    "__int__",
    "__index__",
    "__bool__",
    "__repr__",
    "__format__",
)


def tiny_trainer(root: Path, out: Path, precision: str, **changes) -> Trainer:
    """A one-epoch trainer of a one-block thesis network on the CPU, at `precision`."""
    config = small_config(
        root,
        out,
        precision=precision,
        device="cpu",
        val_sequences=(),
        epochs=1,
        model_overrides=TINY_NET,
        **changes,
    )
    return Trainer(config)


def test_precision_options_and_no_amp(tmp_path):
    parser = train_parser()
    required = ["--dataset", "d", "--out", "o", "--model", "rangeret-thesis"]
    assert config_from_args(parser.parse_args(required)).precision == "auto"
    fp32 = config_from_args(parser.parse_args([*required, "--precision", "fp32"]))
    assert fp32.precision == "fp32"
    assert config_from_args(parser.parse_args([*required, "--no-amp"])) == fp32
    assert config_from_args(parser.parse_args([*required, "--no-amp", "--precision", "fp32"])) == (
        fp32
    )
    for other in ("fp16", "bf16"):
        args = parser.parse_args([*required, "--no-amp", "--precision", other])
        with pytest.raises(ValueError, match=f"--no-amp .*--precision {other}"):
            config_from_args(args)
    with pytest.raises(ValueError, match="precision must be one of"):
        TrainConfig(dataset="d", out="o", precision="fp8")
    legacy = TrainConfig(dataset="d", out="o").to_dict()
    del legacy["precision"]
    assert TrainConfig.from_dict({**legacy, "amp": False}).precision == "fp32"
    assert TrainConfig.from_dict({**legacy, "amp": True}).precision == "auto"
    from workers.train_job import build_parser

    job = build_parser().parse_args([*required, "--precision", "bf16"])
    assert config_from_args(job).precision == "bf16"


def test_bf16_and_fp32_training_steps_differ_on_the_cpu(sim_root, tmp_path):
    """The same first step at bf16 and fp32: the network's layers see bf16 only in the first, and
    losses and weights come out different; neither has a gradient scaler."""
    results = {}
    for precision in ("bf16", "fp32"):
        trainer = tiny_trainer(sim_root, tmp_path / precision, precision)
        assert trainer.precision == precision and not trainer.scaler.is_enabled()
        dtypes = set()
        for module in trainer.model.modules():
            if isinstance(module, torch.nn.Linear):
                module.register_forward_hook(lambda m, i, out, seen=dtypes: seen.add(out.dtype))
        losses = trainer.train_step(collate([trainer.train_set[(0, 0)]]))
        results[precision] = (dtypes, losses, trainer.model.state_dict())
    bf16_dtypes, bf16_losses, bf16_weights = results["bf16"]
    fp32_dtypes, fp32_losses, fp32_weights = results["fp32"]
    assert bf16_dtypes == {torch.bfloat16} and fp32_dtypes == {torch.float32}
    assert all(math.isfinite(v) for v in bf16_losses) and bf16_losses != fp32_losses
    assert math.isclose(bf16_losses[0], fp32_losses[0], rel_tol=0.05)
    assert any(not torch.equal(bf16_weights[k], fp32_weights[k]) for k in fp32_weights)
    assert tiny_trainer(sim_root, tmp_path / "fp16", "fp16").scaler.is_enabled()


@pytest.mark.parametrize("precision", ["fp32", "bf16", "fp16"])
def test_a_training_step_reads_the_device_back_once(precision, sim_root, tmp_path, monkeypatch):
    """One `train_step` calls exactly one host read-back: `.tolist()` of its stacked losses.

    Every method of HOST_READS is counted during the step (the second, after the one that fills
    the network's caches). fp16 has the gradient scaler, whose overflow check stays on the device.
    """
    trainer = tiny_trainer(sim_root, tmp_path / "run", precision)
    batch = collate([trainer.train_set[(0, 0)]])
    trainer.train_step(batch)
    calls = []
    for name in HOST_READS:
        original = getattr(torch.Tensor, name)

        def counted(self, *args, _name=name, _original=original, **kwargs):
            calls.append(_name)
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(torch.Tensor, name, counted)
    values = trainer.train_step(batch)
    monkeypatch.undo()
    assert calls == ["tolist"]
    assert len(values) == 4 and all(isinstance(v, float) for v in values)
    assert trainer.epoch_batches == 2 and trainer.epoch_confusion.sum() == 2 * 16 * 256


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("precision", ["fp32", "bf16", "fp16"])
def test_a_cuda_training_step_synchronises_once(precision, sim_root, tmp_path):
    """torch's sync debug mode reports every operation that waits for the GPU: one step (after a
    warm-up step) has exactly one, the read-back of its losses."""
    trainer = Trainer(
        small_config(
            sim_root,
            tmp_path / "run",
            precision=precision,
            device="cuda",
            val_sequences=(),
            epochs=1,
            model_overrides=TINY_NET,
        )
    )
    batch = {k: v.pin_memory() for k, v in collate([trainer.train_set[(0, 0)]]).items()}
    trainer.train_step(batch)
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            trainer.train_step(batch)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    syncs = [w for w in caught if "synchroniz" in str(w.message)]
    assert len(syncs) == 1, [str(w.message) for w in syncs]


def test_the_precision_is_recorded_and_pinned_on_resume(sim_root, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="rangeret.training")
    out = tmp_path / "run"
    tiny_trainer(sim_root, out, "bf16", max_steps=2).fit(until_step=1)
    assert "in bf16" in caplog.text
    meta = load_checkpoint(out / "last.pt").checkpoint_info.metadata
    assert meta["precision"] == "bf16" and meta["train_config"]["precision"] == "bf16"
    state = torch.load(out / STATE, weights_only=True)
    assert state["config"]["precision"] == "bf16" and state["scaler"] == {}
    auto_here = auto_choice("cpu").precision  # bf16 on a CPU with AMX or AVX-512 bf16
    others = ("fp32", "fp16") if auto_here == "bf16" else ("fp32", "auto", "fp16")
    for other in others:
        with pytest.raises(ValueError, match=r"precision: 'bf16' -> '(fp32|fp16)'"):
            tiny_trainer(sim_root, out, other, max_steps=2, resume=True)
    resumed = tiny_trainer(sim_root, out, "bf16", max_steps=2, resume=True)
    assert resumed.step == 1 and resumed.precision == "bf16"
    auto = tiny_trainer(sim_root, tmp_path / "auto", "auto", max_steps=1)
    assert auto.precision == auto_here and auto.config.precision == auto_here


# Dataset profiles ------------------------------------------------------------------------------

#: Each profile's tiny tree: (training sequences, validation sequences) as given on the command
#: line (ids the profile's layout pads), and the scans written per sequence on disk.
PROFILE_RUNS = {
    "pandaset": (["1"], ["5"], {"001": 2, "005": 1}),
    "semantic-poss": (["0"], ["2"], {"00": 2, "02": 1}),
}
#: The resolution of the profile runs (PandaSet: 16 lasers, ids 0..15).
TINY = {"height": 16, "width": 128}


def train_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    return parser


@pytest.fixture(scope="module")
def profile_roots(tmp_path_factory) -> dict[str, Path]:
    """Each profile's tiny simulated tree, in its layout, point record and raw ids (16 x 128)."""
    roots = {}
    for name, (_, _, counts) in PROFILE_RUNS.items():
        profile = load_profile(name)
        sensor = SensorConfig.for_profile(profile.with_overrides(**TINY), azimuth_steps=128)
        root = tmp_path_factory.mktemp(name)
        simulate_dataset(
            root, counts, labelled=list(counts), sensor=sensor, seed=4, profile=profile
        )
        roots[name] = root
    return roots


def test_train_options_take_a_profile_and_leave_the_rest_to_it(tmp_path, monkeypatch):
    parser = train_parser()
    required = ["--dataset", "d", "--out", "o", "--model", "rangeret-thesis"]
    plain = config_from_args(parser.parse_args(required))
    assert plain.profile == "semantickitti"
    assert (plain.height, plain.width, plain.fov_up, plain.fov_down) == (None,) * 4
    assert plain.dataset_profile() == load_profile("semantickitti")
    file = tmp_path / "campus.yaml"
    file.write_text(load_profile("pandaset").to_yaml())
    monkeypatch.chdir(tmp_path)
    argv = [*required, "--profile", "campus.yaml"]
    config = config_from_args(parser.parse_args([*argv, "--height", "16", "--fov-up", "10"]))
    assert config.profile == str(file) and Path(config.profile).is_absolute()
    assert TrainConfig.from_dict(config.to_dict()) == config
    profile = config.dataset_profile()
    assert profile.name == "pandaset" and profile.projection.row == "laser_id"
    assert (profile.projection.height, profile.projection.width) == (16, 1024)
    assert (profile.projection.fov_up, profile.projection.fov_down) == (10.0, -25.0)
    named = config_from_args(parser.parse_args([*required, "--profile", "semantic-poss"]))
    assert named.profile == "semantic-poss" and named.dataset_profile().num_classes == 14
    resolved = named.with_projection(named.dataset_profile().projection)
    assert (resolved.height, resolved.width, resolved.fov_up) == (40, 2048, 7.0)


def test_pandaset_samples_keep_laser_rows_and_the_unlabeled_class(profile_roots):
    profile = load_profile("pandaset").with_overrides(**TINY)
    scans = find_scans(profile_roots["pandaset"], ["1"], "train", profile)
    assert [s.key for s in scans] == ["001/000000", "001/000001"]
    ds = RangeDataset(
        scans,
        profile.projection,
        profile.labels,
        augment=True,
        with_points=True,
        points=profile.points,
    )
    points, classes = ds.points_and_classes(0)
    assert points.shape[1] == 5 and classes.max() < profile.num_classes
    moved = augment_points(points, np.random.default_rng(3))
    assert np.array_equal(moved[:, 2:], points[:, 2:])
    assert not np.allclose(moved[:, :2], points[:, :2])
    sample = ds[(1, 0)]
    # Augmented or not, a point's row is its laser id; empty pixels hold the unlabeled class 14.
    px = sample["proj_x"]
    valid = px >= 0
    assert np.array_equal(sample["proj_y"][valid], points[valid, 4].astype(np.int64))
    assert np.all(sample["label"][~sample["mask"]] == 14) and (~sample["mask"]).any()
    assert np.isin(0, sample["label"][sample["mask"]])


@pytest.mark.parametrize("name", sorted(PROFILE_RUNS))
def test_training_on_a_profile_records_it(name, profile_roots, tmp_path):
    """`rangeret train --profile NAME` on the profile's tree: the checkpoints record the profile,
    the predictor runs with it and refuses another, and a resume with another profile fails."""
    train, valid, _ = PROFILE_RUNS[name]
    out = tmp_path / "run"
    argv = [
        "--dataset", str(profile_roots[name]), "--profile", name,
        "--model", "rangeret-thesis", "--out", str(out),
        "--height", str(TINY["height"]), "--width", str(TINY["width"]),
        "--train-sequences", *train, "--val-sequences", *valid,
        "--epochs", "1", "--max-steps", "2", "--loader-workers", "0",
        "--override", "layers=1", "--override", "dim=16", "--override", "heads=2",
        "--device", "cpu",
    ]  # fmt: skip
    args = train_parser().parse_args(argv)
    args.quiet = True
    assert run_train(args) == 0
    profile = load_profile(name)
    best = out / "best.pt"
    info = load_checkpoint(best).checkpoint_info
    assert info.config["num_classes"] == profile.num_classes
    assert info.profile["name"] == name
    assert (info.profile["sensor"]["height"], info.profile["sensor"]["width"]) == (16, 128)
    assert info.profile["sensor"]["row"] == profile.projection.row
    assert info.profile["labels"] == profile.to_dict()["labels"]
    assert info.metadata["train_config"]["profile"] == name
    assert info.metadata["metrics"]["val_miou_knn"] >= 0

    predictor = Predictor.from_checkpoint(best, device="cpu")
    assert predictor.profile.name == name and predictor.num_classes == profile.num_classes
    assert predictor.projection_config == profile.with_overrides(**TINY).projection
    scan = discover(
        profile_roots[name], [profile.layout.normalise(valid[0])], layout=profile.layout
    )
    points = read_scan(scan.scans[0].scan_path, profile.points)
    labels = predictor.predict(points).labels
    assert len(labels) == len(points) and set(np.unique(labels)) <= set(
        profile.labels.class_raw_ids
    )
    other = "semantickitti"
    with pytest.raises(CheckpointError, match=f"{name} profile.*{other} profile"):
        Predictor.from_checkpoint(best, profile=load_profile(other), device="cpu")

    args.profile = "pandaset" if name != "pandaset" else "semantic-poss"
    args.resume = True
    with pytest.raises(ValueError, match=f"started with the {name} profile.*{args.profile}"):
        run_train(args)


@pytest.mark.slow
def test_ray_train_with_two_cpu_workers(sim_root, tmp_path):
    ray = pytest.importorskip("ray")
    from workers.train_job import run_ray

    config = small_config(
        sim_root,
        tmp_path / "ray-run",
        model="rangeret-cir",
        epochs=1,
        model_overrides=(("layers", 2),),
    )
    ray.init(address="local", num_cpus=2, num_gpus=0, include_dashboard=False)
    try:
        out = run_ray(config, workers=2)
    finally:
        ray.shutdown()
    model = load_checkpoint(out / "last.pt")
    meta = model.checkpoint_info.metadata
    assert meta["world_size"] == 2 and meta["step"] == 2 and meta["epoch_complete"]
    assert model.config.name == "rangeret-cir" and model.config.layers == 2
    assert (
        load_checkpoint(out / "best.pt").checkpoint_info.metadata["best"]["metric"]
        == "val_miou_knn"
    )
    assert len((out / "steps.csv").read_text().splitlines()) == 3


@pytest.mark.slow
def test_overfitting_the_real_scan(tmp_path):
    """The thesis network at 32 x 512 learns the real scan's range image to >= 95 % pixel accuracy
    in well under 3 minutes (on one thread): labels, projection, losses and optimiser line up."""
    scan = data_path("semantickitti-scan", "000000.bin")
    labels = data_path("semantickitti-scan", "000000.label")
    # One epoch of 150 steps: the scan under 150 names (links), so the run saves only once.
    steps = 150
    root = tmp_path / "data"
    velodyne_dir(root, "00", layout=KITTI_LAYOUT).mkdir(parents=True)
    labels_dir(root, "00", layout=KITTI_LAYOUT).mkdir(parents=True)
    for i in range(steps):
        (velodyne_dir(root, "00", layout=KITTI_LAYOUT) / f"{i:06d}.bin").symlink_to(scan)
        (labels_dir(root, "00", layout=KITTI_LAYOUT) / f"{i:06d}.label").symlink_to(labels)
    config = small_config(
        root,
        tmp_path / "out",
        height=32,
        width=512,
        val_sequences=(),
        augment=False,
        class_weighting="none",
        epochs=1,
        lr=1e-3,
        max_lr=3e-3,
        warmup=0.1,
    )
    start = time.perf_counter()
    trainer = Trainer(config, device="cpu")
    trainer.fit()
    sample = trainer.train_set[0]
    model = load_checkpoint(tmp_path / "out" / "last.pt")
    with torch.inference_mode():
        pred = model(torch.from_numpy(sample["image"])[None])[0].argmax(0).numpy()
    elapsed = time.perf_counter() - start
    labelled = sample["label"] > 0
    accuracy = float((pred[labelled] == sample["label"][labelled]).mean())
    print(
        f"over-fit: accuracy {accuracy:.4f} on {labelled.sum()} labelled pixels in {elapsed:.1f} s"
    )
    assert accuracy >= 0.95
