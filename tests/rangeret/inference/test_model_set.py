"""Models files: names, the default, each entry's options over the server's, and one sentence
naming the file and the field for everything wrong."""

from __future__ import annotations

import pytest

from rangeret.inference.model_set import (
    DEFAULT_NAME,
    ModelSet,
    ModelsFileError,
    UnknownModelError,
    load_models_file,
)
from rangeret.inference.spec import InferenceSpec


def test_a_file_names_each_model_over_the_servers_options(tmp_path):
    path = tmp_path / "models.yaml"
    path.write_text(
        "default: kitti\n"
        "models:\n"
        "  kitti: {checkpoint: rangeret-kitti-657}\n"
        "  panda: {checkpoint: /models/panda.pt, profile: pandaset, knn: false}\n"
    )
    base = InferenceSpec(device="cpu", batch_size=4, knn=True)
    models = load_models_file(path, base)
    assert models.names == ["kitti", "panda"] and models.default == "kitti"
    assert models.spec() == InferenceSpec(
        checkpoint="rangeret-kitti-657", device="cpu", batch_size=4
    )
    panda = models.spec("panda")
    assert panda.profile == "pandaset" and panda.knn is False and panda.device == "cpu"
    assert panda.batch_size == 4
    assert ModelSet.from_mapping(models.to_mapping(), base) == models
    with pytest.raises(
        UnknownModelError, match="there is no model 'poss'; the models are kitti, panda"
    ):
        models.spec("poss")


def test_one_model_needs_no_default_and_a_plain_spec_is_named_default(tmp_path):
    models = ModelSet.from_mapping({"models": {"only": {"checkpoint": "w.pt"}}})
    assert models.default == "only" and models.spec().checkpoint == "w.pt"
    single = ModelSet.single(InferenceSpec(checkpoint="w.pt"))
    assert single.names == [DEFAULT_NAME] and single.spec(None).checkpoint == "w.pt"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("[a, b]\n", "must be a mapping with `models` (and `default`), got list"),
        ("models: {}\n", "models: must map each model's name to its options"),
        ("models: {a: {}}\nextra: 1\n", "extra: is not a field (expected: default, models)"),
        ("models: {Kitti: {}}\n", "models: 'Kitti' is not a model name"),
        ("models: {a/b: {}}\n", "models: 'a/b' is not a model name"),
        ("models: {a: {}, b: {}}\n", "default: is missing; name one of a, b"),
        ("default: c\nmodels: {a: {}, b: {}}\n", "default: 'c' is not one of the models (a, b)"),
        ("models: {a: [1]}\n", "models.a: must be a mapping of network options, got list"),
        ("models: {a: {batch_size: 8}}\n", "models.a.batch_size: is the server's setting"),
        ("models: {a: {bogus: 1}}\n", "unknown network option bogus of models.a in"),
        ("models: {a: {height: tall}}\n", "height of models.a in"),
    ],
)
def test_everything_wrong_is_one_sentence_naming_the_file(tmp_path, text, problem):
    path = tmp_path / "models.yaml"
    path.write_text(text)
    with pytest.raises(ModelsFileError) as caught:
        load_models_file(path)
    message = str(caught.value)
    assert problem in message and str(path) in message and "\n" not in message


def test_a_name_may_be_63_characters_not_64():
    assert ModelSet.from_mapping({"models": {"a" * 63: {}}}).names == ["a" * 63]
    with pytest.raises(ModelsFileError, match="is not a model name"):
        ModelSet.from_mapping({"models": {"a" * 64: {}}})
