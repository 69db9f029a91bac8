"""The fields a network run and a training run share, declared once in
`rangeret.inference.network_fields`: both classes take each one's kind, allowed values and help
from it, and say the same sentence about a bad value."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import typing

import numpy as np
import pytest

from rangeret.dataset.fields import is_int, is_number
from rangeret.inference import InferenceSpec, InferenceSpecError
from rangeret.inference.network_fields import MODELS, FieldSchema
from rangeret.models.configs import list_models
from rangeret.training.config import TrainConfig, TrainConfigError
from rangeret.training.config_file import split_optional

SHARED = (
    "profile",
    "model",
    "height",
    "width",
    "fov_up",
    "fov_down",
    "batch_size",
    "device",
    "precision",
)


def _schemas(cls: type) -> dict[str, FieldSchema]:
    return {f.name: f.metadata["schema"] for f in dataclasses.fields(cls) if "schema" in f.metadata}


def test_the_nine_shared_fields_are_declared_once_for_both_classes():
    spec, train = _schemas(InferenceSpec), _schemas(TrainConfig)
    assert set(spec) == {f.name for f in dataclasses.fields(InferenceSpec)}
    assert set(train) == set(SHARED) and all(spec[name].name == name for name in spec)
    hints = typing.get_type_hints(TrainConfig)
    for name in SHARED:
        ours, theirs = spec[name], train[name]
        same = dataclasses.replace(theirs, default=ours.default, default_text=ours.default_text)
        assert same == ours and split_optional(hints[name])[0] is ours.kind
    # Only where a training run means another default does it say so; a network run is fp32
    # unless asked, a training run mixed precision by the auto rule.
    assert {n for n in SHARED if spec[n] != train[n]} == {"profile", "model", "precision"}
    assert (spec["precision"].default, train["precision"].default) == ("fp32", "auto")


def test_the_networks_named_are_those_the_models_build():
    assert tuple(list_models()) == MODELS


@pytest.mark.parametrize(
    ("values", "sentence"),
    [
        ({"batch_size": 0}, "batch_size must be at least 1, got 0"),
        ({"height": 0}, "height must be at least 1, got 0"),
        ({"width": 9000}, "width must be at most 8192, got 9000"),
        ({"device": "tpu"}, "device must be one of auto, cpu, cuda, got 'tpu'"),
        ({"precision": "fp8"}, "precision must be one of auto, fp32, fp16, bf16, got 'fp8'"),
        ({"model": "resnet"}, "model must be one of rangeret-cir, rangeret-thesis, got 'resnet'"),
    ],
)
def test_both_classes_say_the_same_sentence_about_a_bad_value(values, sentence):
    with pytest.raises(InferenceSpecError, match=f"^{sentence}$"):
        InferenceSpec(**values)
    with pytest.raises(TrainConfigError, match=f"^{sentence}$"):
        TrainConfig(dataset="d", out="o", **values)


def test_an_integer_is_never_a_bool():
    assert is_int(3) and is_int(np.int64(3)) and not is_int(True) and not is_int(3.0)
    assert is_number(3) and is_number(0.5) and is_number(np.float32(1)) and not is_number(False)
    assert not is_int("3") and not is_number("0.5")


def test_the_package_names_the_spec_without_importing_it():
    code = (
        "import sys, rangeret.inference as p; "
        "assert 'rangeret.inference.spec' not in sys.modules and 'torch' not in sys.modules; "
        "from rangeret.inference import InferenceSpec; "
        "assert InferenceSpec is sys.modules['rangeret.inference.spec'].InferenceSpec; "
        "assert 'torch' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
