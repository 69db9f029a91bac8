"""The bundled label configuration against the official one, and raw id mapping."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import yaml

from rangeret import DATA_DIR
from rangeret.dataset.labels import (
    LabelConfigError,
    load_label_config,
    parse_label_config,
    semantickitti,
)
from rangeret.dataset.profiles import DatasetProfile, ProfileError, load_profile
from rangeret.exceptions import ConfigError
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


def _official(tmp_path, edit):
    data = yaml.safe_load(data_path("semantic-kitti.yaml").read_text())
    edit(data)
    path = tmp_path / "labels.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_every_source_parses_to_the_same_configuration():
    kitti = semantickitti()
    block = load_profile("semantickitti").to_dict()
    profile = DatasetProfile.from_dict(block, "profile semantickitti")
    assert profile.labels == kitti
    assert load_label_config(data_path("semantic-kitti.yaml")).raw_to_class == kitti.raw_to_class
    assert parse_label_config(kitti.to_dict(), "checkpoint c.pt") == kitti


def test_errors_name_the_source_and_the_field_in_one_shape(tmp_path):
    kitti = semantickitti()
    bad_yaml = _official(tmp_path, lambda d: d["learning_map"].update({300: 25}))
    stored = kitti.to_dict()
    stored["raw_to_class"]["300"] = 25
    project = json.loads((DATA_DIR / "semantickitti.json").read_text())
    project["raw_labels"][2]["class"] = 25
    bad_json = tmp_path / "labels.json"
    bad_json.write_text(json.dumps(project))
    block = load_profile("semantickitti").to_dict()
    block["labels"]["raw_labels"][2]["class"] = 25
    raw = project["raw_labels"][2]["id"]
    cases = [
        (lambda: load_label_config(bad_yaml), f"{bad_yaml}: learning_map: raw id 300"),
        (
            lambda: parse_label_config(stored, "checkpoint c.pt"),
            "checkpoint c.pt: raw_to_class: raw id 300",
        ),
        (lambda: load_label_config(bad_json), f"{bad_json}: raw_labels[2].class: raw id {raw}"),
        (
            lambda: DatasetProfile.from_dict(block, "profile p"),
            f"profile p: labels.raw_labels[2].class: raw id {raw}",
        ),
    ]
    for parse, start in cases:
        with pytest.raises(
            LabelConfigError if "profile p" not in start else ProfileError
        ) as caught:
            parse()
        assert isinstance(caught.value, ConfigError)
        message = str(caught.value)
        assert message.startswith(start), message
        assert message.endswith("maps to unknown class 25 (must be a class 0..19)"), message


def test_a_missing_field_and_an_unreadable_file_are_named(tmp_path):
    no_inverse = _official(tmp_path, lambda d: d.pop("learning_map_inv"))
    with pytest.raises(
        LabelConfigError, match=re.escape(f"{no_inverse}: learning_map_inv: is missing")
    ):
        load_label_config(no_inverse)
    gap = _official(tmp_path, lambda d: d["learning_map_inv"].pop(3))
    with pytest.raises(
        LabelConfigError, match=re.escape("learning_map_inv: must cover classes 0..N-1")
    ):
        load_label_config(gap)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(LabelConfigError, match=re.escape(f"{broken}: cannot read")):
        load_label_config(broken)
    with pytest.raises(LabelConfigError, match=re.escape("checkpoint x: raw_to_class: is missing")):
        parse_label_config({"class_names": [], "class_raw_ids": [], "ignored": []}, "checkpoint x")
