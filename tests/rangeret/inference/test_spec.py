"""`InferenceSpec`: the network options written once, read from a mapping, a JSON option or the
command line, each bad value named as its source spells it."""

from __future__ import annotations

import argparse
import json

import pytest

from rangeret.inference.spec import (
    RUN,
    WEIGHTS,
    InferenceSpec,
    InferenceSpecError,
    field_names,
    flag,
    group_fields,
)
from rangeret.options import add_network_options, add_weights_options

#: The command line's network options before they were derived from the spec's fields.
NETWORK_FLAGS = {
    "--profile",
    "--model",
    "--checkpoint",
    "--height",
    "--width",
    "--fov-up",
    "--fov-down",
    "--batch-size",
    "--no-knn",
    "--device",
    "--precision",
    "--backend",
    "--onnx",
    "--tta-flip",
    "--tta-shifts",
    "--panoptic",
    "--cluster-angle",
    "--min-cluster-points",
}


def _parser(add=add_network_options) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(exit_on_error=False)
    add(parser)
    return parser


def _flags(parser: argparse.ArgumentParser) -> set[str]:
    return {s for a in parser._actions for s in a.option_strings if s not in ("-h", "--help")}


def test_every_field_has_its_option_and_every_option_its_field():
    assert _flags(_parser()) == NETWORK_FLAGS
    assert {flag(name) for name in field_names()} == NETWORK_FLAGS
    assert _flags(_parser(add_weights_options)) == {
        "--checkpoint",
        "--profile",
        "--model",
        "--height",
        "--width",
        "--fov-up",
        "--fov-down",
    }


def test_a_spec_goes_through_json_and_back():
    spec = InferenceSpec(
        checkpoint="/models/w.pt",
        profile="pandaset",
        model="rangeret-cir",
        height=32,
        width=256,
        fov_up=3.5,
        fov_down=-20.0,
        batch_size=8,
        knn=False,
        device="cpu",
        precision="bf16",
        tta_flip=True,
        tta_shifts=2,
        panoptic=True,
        cluster_angle=12.5,
        min_cluster_points=20,
    )
    text = json.dumps(spec.to_mapping())
    assert InferenceSpec.from_mapping(json.loads(text)) == spec
    assert InferenceSpec.from_mapping({}) == InferenceSpec() and InferenceSpec().to_mapping() == {}
    assert set(group_fields(WEIGHTS)) | set(group_fields(RUN)) == set(field_names())
    assert spec.knn_settings is None and spec.tta is not None and spec.tta.shifts == 2
    assert InferenceSpec().knn_settings is not None and InferenceSpec().tta is None


def test_the_command_line_and_a_mapping_give_the_same_spec():
    argv = ["--checkpoint", "w.pt", "--height", "32", "--no-knn", "--batch-size", "4"]
    argv += ["--fov-up", "3", "--tta-flip"]
    from_args = InferenceSpec.from_args(_parser().parse_args(argv))
    mapping = {"checkpoint": "w.pt", "height": 32, "knn": False, "batch_size": 4}
    mapping.update(fov_up=3, tta_flip=True)
    assert from_args == InferenceSpec.from_mapping(mapping)
    assert from_args.fov_up == 3.0 and isinstance(from_args.fov_up, float)
    assert InferenceSpec.from_args(_parser().parse_args([])) == InferenceSpec()
    assert InferenceSpec.from_mapping({"batch_size": "8", "fov_down": "-25"}).batch_size == 8


@pytest.mark.parametrize(
    ("values", "sentence"),
    [
        ({"batch_size": "eight"}, "batch_size takes an integer, got 'eight'"),
        ({"bogus": 1}, "unknown network option bogus; the known ones are checkpoint, profile"),
        ({"batch_size": 0}, "batch_size must be at least 1, got 0"),
        ({"tta_shifts": -1}, "tta_shifts must not be negative, got -1"),
        ({"knn": "no"}, "knn takes true or false, got 'no'"),
        ({"height": True}, "height takes an integer, got True"),
        ({"device": "tpu"}, "device must be one of auto, cpu, cuda, got 'tpu'"),
        ({"fov_up": float("nan")}, "fov_up takes a number, got nan"),
        ({"checkpoint": 7}, "checkpoint takes a string, got 7"),
        ({"height": 100_000}, "height must be at most 512, got 100000"),
        ({"width": "100000"}, "width must be at most 8192, got 100000"),
    ],
)
def test_a_bad_mapping_is_one_sentence_naming_its_key(values, sentence):
    with pytest.raises(InferenceSpecError) as caught:
        InferenceSpec.from_mapping(values)
    assert str(caught.value).startswith(sentence)
    assert "--" not in str(caught.value)


def test_a_bad_option_is_named_as_the_command_line_spells_it():
    parser = _parser()
    with pytest.raises(InferenceSpecError, match=r"^--batch-size must be at least 1, got 0$"):
        InferenceSpec.from_args(parser.parse_args(["--batch-size", "0"]))
    with pytest.raises(InferenceSpecError, match=r"^--tta-shifts must not be negative, got -2$"):
        InferenceSpec.from_args(parser.parse_args(["--tta-shifts", "-2"]))
    with pytest.raises(InferenceSpecError, match=r"^--precision fp16 cannot run with --backend"):
        InferenceSpec.from_args(
            parser.parse_args(["--backend", "onnxruntime", "--precision", "fp16"])
        )
    with pytest.raises(InferenceSpecError, match=r"^precision fp16 cannot run with backend onnx"):
        InferenceSpec.from_mapping({"backend": "onnxruntime", "precision": "fp16"})


def test_where_says_whose_mapping_it_is():
    with pytest.raises(InferenceSpecError, match=r"^batch_size in --inference-spec takes an int"):
        InferenceSpec.from_mapping({"batch_size": "eight"}, where=" in --inference-spec")
