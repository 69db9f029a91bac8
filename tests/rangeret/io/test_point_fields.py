"""`rangeret.io.point_fields`: record values found by name or alias, `--field` overrides, the
reflectance fill, invalid points kept in place, and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.io.point_fields import PointFieldsError, parse_field_overrides, to_record
from rangeret.io.scans import KITTI_RECORD, PointRecord

PANDA = PointRecord(("x", "y", "z", "intensity", "laser_id"))


def _columns(n: int = 5, **extra: np.ndarray) -> dict[str, np.ndarray]:
    base = {k: np.arange(n, dtype=np.float64) + i for i, k in enumerate("xyz")}
    return {**base, **extra}


def test_aliases_fill_the_record_in_their_order():
    ring = np.arange(5, dtype=np.uint16)
    cloud = to_record(
        _columns(intensity=np.full(5, 0.5), ring=ring, reflectivity=np.full(5, 9.0)),
        record=PANDA,
        source="a.pcd",
        reflectance_fill=0.2,
    )
    assert cloud.sources == {
        "x": "x",
        "y": "y",
        "z": "z",
        "intensity": "intensity",
        "laser_id": "ring",
    }
    assert cloud.points.dtype == np.float32 and cloud.points.shape == (5, 5)
    assert np.array_equal(cloud.points[:, 4], ring.astype(np.float32))
    kitti = to_record(
        _columns(Intensity=np.full(5, 0.25)), record=KITTI_RECORD, source="b", reflectance_fill=0.2
    )
    assert kitti.sources["remission"] == "Intensity"  # names match without regard to case
    assert (kitti.points[:, 3] == 0.25).all()


def test_an_override_names_the_field_and_a_missing_one_is_an_error():
    columns = _columns(intensity=np.zeros(5), refl=np.ones(5))
    cloud = to_record(
        columns,
        record=KITTI_RECORD,
        source="c",
        reflectance_fill=0.2,
        overrides={"remission": "refl"},
    )
    assert cloud.sources["remission"] == "refl" and (cloud.points[:, 3] == 1).all()
    with pytest.raises(
        PointFieldsError, match=r"c: has no field 'gone' \(named by --field remission"
    ):
        to_record(
            columns,
            record=KITTI_RECORD,
            source="c",
            reflectance_fill=0.2,
            overrides={"remission": "gone"},
        )


def test_a_cloud_without_reflectance_gets_the_fill_value():
    cloud = to_record(_columns(), record=KITTI_RECORD, source="d", reflectance_fill=0.21)
    assert cloud.sources["remission"] == "fill 0.21"
    assert np.allclose(cloud.points[:, 3], 0.21)
    assert cloud.describe() == {
        "fields": {"x": "x", "y": "y", "z": "z", "remission": "fill 0.21"},
        "invalid_points": 0,
    }


def test_a_missing_position_or_laser_id_is_refused_in_one_line():
    columns = _columns()
    del columns["z"]
    with pytest.raises(PointFieldsError) as exc:
        to_record(columns, record=KITTI_RECORD, source="e.ply", reflectance_fill=0.2)
    assert "e.ply: has no z field" in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(PointFieldsError, match="laser_id or ring"):
        to_record(_columns(), record=PANDA, source="f", reflectance_fill=0.2)
    with pytest.raises(PointFieldsError, match="different numbers of points"):
        to_record(
            {**_columns(), "z": np.zeros(4)}, record=KITTI_RECORD, source="g", reflectance_fill=0
        )


def test_non_finite_points_stay_in_place_marked_invalid():
    x = np.arange(6, dtype=np.float32)
    x[[1, 4]] = [np.nan, np.inf]
    cloud = to_record(
        {"x": x, "y": np.zeros(6), "z": np.zeros(6)},
        record=KITTI_RECORD,
        source="h",
        reflectance_fill=0.2,
    )
    assert cloud.num_points == 6 and cloud.num_invalid == 2
    assert cloud.valid.tolist() == [True, False, True, True, False, True]
    assert np.isnan(cloud.points[1, 0])


@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("remission", "expected NAME=FIELD"),
        ("=i", "expected NAME=FIELD"),
        ("remission=", "expected NAME=FIELD"),
        ("laser_id=ring", "'laser_id' is not a value of the point record"),
    ],
)
def test_bad_field_options_are_refused(item, message):
    with pytest.raises(PointFieldsError, match=message):
        parse_field_overrides([item], record=KITTI_RECORD)


def test_field_options_parse():
    assert parse_field_overrides([" remission = i "], record=KITTI_RECORD) == {"remission": "i"}
    assert parse_field_overrides(None, record=KITTI_RECORD) == {}
