"""Error sentences: validation errors as one readable sentence."""

from __future__ import annotations

from service.http.errors import validation_sentence


def test_validation_sentences():
    errors = [
        {"loc": ("query", "knn"), "msg": "Input should be a valid boolean"},
        {"loc": ("body",), "msg": "x"},
    ]
    assert validation_sentence(errors) == (
        "The query parameter 'knn' is invalid: Input should be a valid boolean (and 1 more problem(s))."
    )
    assert validation_sentence(
        [{"loc": (), "msg": "Value error, give either 'split' or 'sequences'"}], "body"
    ) == ("The request body is invalid: give either 'split' or 'sequences'.")
