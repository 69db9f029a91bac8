"""Spherical projection: agreement with the published convention, closest-wins and round trips."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.dataset.projection import (
    CHANNEL_MEANS,
    CHANNEL_STDS,
    ProjectionConfig,
    ProjectionError,
    project,
)
from rangeret.io.scans import read_labels, read_scan
from tests.support.paths import data_path


@pytest.fixture(scope="module")
def scan(real_scan_path):
    return read_scan(real_scan_path)


def test_pixels_match_the_published_projection(scan):
    ref = np.load(data_path("knn-semantickitti-scan.npz"))
    p = project(scan, 64, 1024)
    np.testing.assert_array_equal(p.proj_x, ref["proj_x"])
    np.testing.assert_array_equal(p.proj_y, ref["proj_y"])
    np.testing.assert_array_equal(p.unproj_range, ref["unproj_range"])
    np.testing.assert_array_equal(p.proj_range, ref["proj_range"])


@pytest.mark.parametrize("width", [1024, 2048])
def test_coverage_counts_every_occupied_pixel(scan, width):
    p = project(scan, 64, width)
    occupied = np.unique(p.proj_y * width + p.proj_x).size
    assert p.mask.sum() == occupied
    assert (p.proj_range >= 0).sum() == occupied
    assert p.image.shape == (5, 64, width) and p.image.dtype == np.float32
    share = occupied / (64 * width)
    assert (0.7 < share < 0.85) if width == 1024 else (0.65 < share < 0.8)


def test_real_scan_coverage(scan):
    # 50,901 pixels at 64 x 1024 is also what the published projection fills (the fixture's range image).
    assert project(scan, 64, 1024).mask.sum() == 50_901
    assert project(scan, 64, 2048).mask.sum() > project(scan, 64, 1024).mask.sum()


def test_closest_point_wins_every_pixel(scan):
    p = project(scan, 64, 1024)
    pixel = p.proj_y * 1024 + p.proj_x
    nearest = np.full(64 * 1024, np.inf, np.float32)
    np.minimum.at(nearest, pixel, p.unproj_range)
    flat = p.proj_range.reshape(-1)
    np.testing.assert_array_equal(flat[p.mask.reshape(-1)], nearest[np.isfinite(nearest)])
    winners = p.proj_idx[p.mask]
    np.testing.assert_array_equal(p.unproj_range[winners], p.proj_range[p.mask])


def test_ties_go_to_the_lower_index():
    a = np.array([5.0, 1.0, 0.0, 0.3], np.float32)
    b = np.array([5.0, 1.0, 0.0, 0.9], np.float32)
    far = np.array([9.0, 1.8, 0.0, 0.1], np.float32)
    for order in ([a, b, far], [far, b, a]):
        p = project(np.stack(order), 64, 1024)
        assert p.mask.sum() == 1
        winner = int(p.proj_idx[p.mask][0])
        assert winner == (0 if order[0] is a else 1)
        assert p.image[4][p.mask][0] == pytest.approx(
            (order[winner][3] - CHANNEL_MEANS[4]) / CHANNEL_STDS[4]
        )


def test_label_round_trip_is_lossless(scan, real_label_path):
    labels = read_labels(real_label_path, len(scan))
    p = project(scan, 64, 1024)
    image = p.to_image(labels)
    back = p.to_points(image)
    assert back.shape == labels.shape
    winners = p.proj_idx[p.mask]
    np.testing.assert_array_equal(back[winners], labels[winners])
    pixel_owner = p.proj_idx[p.proj_y, p.proj_x]
    np.testing.assert_array_equal(back, labels[pixel_owner])
    assert (back == labels).mean() > 0.9


def test_invalid_points_are_kept_out_but_labelled():
    pts = np.array(
        [
            [10, 0, 0, 0.5],
            [0, 0, 0, 0.2],
            [np.nan, 1, 1, 0.1],
            [0, 10, -1, np.inf],
            [-3, -4, 0, 0.4],
        ],
        np.float32,
    )
    p = project(pts, 16, 128)
    assert p.proj_x.tolist()[1:4] == [-1, -1, -1]
    assert p.proj_y.tolist()[1:4] == [-1, -1, -1]
    assert p.valid.tolist() == [True, False, False, False, True]
    assert p.mask.sum() == 2
    out = p.to_points(np.full((16, 128), 7, np.int64))
    assert out.tolist() == [7, 0, 0, 0, 7]
    assert np.isfinite(p.image).all()


def test_image_channels_are_normalised_and_empty_pixels_zero(scan):
    p = project(scan[:5000], 32, 256, fov_up=5.0, fov_down=-30.0)
    winners = p.proj_idx[p.mask]
    raw = np.column_stack([p.unproj_range[winners], scan[winners]])
    expected = (raw - np.array(CHANNEL_MEANS, np.float32)) / np.array(CHANNEL_STDS, np.float32)
    np.testing.assert_allclose(p.image[:, p.mask].T, expected, rtol=1e-6, atol=1e-6)
    assert (p.image[:, ~p.mask] == 0).all()
    assert p.proj_x.max() < 256 and p.proj_y.max() < 32 and p.proj_x.min() >= 0


def test_points_outside_the_fov_are_clamped_to_the_border_rows():
    pts = np.array([[10, 0, 10, 0], [10, 0, -10, 0]], np.float32)  # +45 and -45 degrees
    p = project(pts, 64, 1024)
    assert p.proj_y.tolist() == [0, 63]


def test_bad_shapes_and_configs_are_rejected():
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        project(np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match="image size"):
        project(np.zeros((3, 4), np.float32), height=0)
    with pytest.raises(ValueError, match="field of view"):
        project(np.zeros((3, 4), np.float32), fov_up=0, fov_down=0)


def test_a_projection_is_checked_where_it_is_made(scan):
    """What kNN refinement relies on is checked once, when a `Projection` is made."""
    from dataclasses import asdict

    from rangeret.dataset.projection import Projection

    fields = asdict(project(scan[::50], 8, 32))
    Projection(**fields)  # as made
    x, y = fields["proj_x"], fields["proj_y"]
    cases = [
        ("proj_x", np.where(x == x.max(), 32, x), "width 32"),
        ("proj_x", x - 2, "-1"),
        ("proj_x", x.astype(np.float32), "integers"),
        ("proj_y", np.where(x >= 0, y + 8, -1), r"\[0, 8\)"),
        ("unproj_range", fields["unproj_range"][:-1], "same shape"),
        ("proj_range", fields["proj_range"][0], r"\(H, W\)"),
        ("mask", fields["mask"][:, :-1], "mask"),
        ("image", fields["image"][0], "image"),
    ]
    for name, value, detail in cases:
        with pytest.raises(ValueError, match=name) as raised:
            Projection(**{**fields, name: value})
        assert raised.match(detail)


@pytest.mark.parametrize(("height", "width"), [(100_000, 1024), (64, 100_000), (513, 8193)])
def test_an_image_past_the_largest_is_one_line(height, width):
    with pytest.raises(ProjectionError) as exc:
        ProjectionConfig(height=height, width=width)
    assert str(exc.value) == f"image size must be at most 512 x 8192, got {height} x {width}"
    assert ProjectionConfig(height=512, width=8192).width == 8192
