"""The bundled label configuration against the official one, and raw id mapping."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rangeret.dataset.labels import load_label_config, parse_label_config, semantickitti
from tests.support.paths import data_path


def test_bundled_config_equals_official_yaml():
    official = load_label_config(data_path("semantic-kitti.yaml"))
    ours = semantickitti()
    assert ours.class_names == official.class_names
    assert ours.class_raw_ids == official.class_raw_ids
    assert ours.ignored == official.ignored
    assert ours.raw_to_class == official.raw_to_class
    assert ours.raw_bgr == official.raw_bgr
    assert ours.splits == official.splits
    for raw, share in official.raw_frequency.items():
        assert ours.raw_frequency[raw] == pytest.approx(share, rel=1e-9, abs=1e-15)


def test_semantickitti_facts():
    cfg = semantickitti()
    assert cfg.num_classes == 20
    assert cfg.evaluated_classes == list(range(1, 20))
    assert cfg.class_names[1] == "car" and cfg.class_names[19] == "traffic-sign"
    assert cfg.split("valid") == ("08",)
    assert cfg.split("test") == tuple(f"{i}" for i in range(11, 22))
    assert len(cfg.split("train")) == 10
    with pytest.raises(ValueError, match="unknown split"):
        cfg.split("val")
    assert cfg.class_frequencies().sum() == pytest.approx(1.0, abs=1e-5)


def test_raw_to_class_masks_instances_and_unknown_ids():
    cfg = semantickitti()
    raw = np.array([10, 252, 40 | (5 << 16), 99, 1, 3, 65535], dtype=np.uint32)
    np.testing.assert_array_equal(cfg.to_class(raw), [1, 1, 9, 0, 0, 0, 0])
    np.testing.assert_array_equal(cfg.to_raw(np.array([0, 1, 9, 19])), [0, 10, 40, 81])
    assert cfg.valid_prediction_ids == frozenset(cfg.class_raw_ids)
    assert cfg.class_rgb()[1].tolist() == [100, 150, 245]


def test_dict_round_trip():
    cfg = semantickitti()
    again = parse_label_config(json.loads(json.dumps(cfg.to_dict())), "checkpoint test")
    assert again == cfg
    np.testing.assert_array_equal(again.raw_lut, cfg.raw_lut)
