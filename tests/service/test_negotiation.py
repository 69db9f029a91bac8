"""Content negotiation of the single-scan answer: JSON or raw labels by the Accept header."""

from __future__ import annotations

import pytest

from service.routes.scans import wants_json


@pytest.mark.parametrize(
    ("accept", "json"),
    [
        (None, False),
        ("*/*", False),
        ("application/json", True),
        ("application/json, */*", True),
        ("application/octet-stream, application/json", False),
        ("application/octet-stream;q=0.5, application/json", True),
        ("application/json;q=0", False),
        ("text/html", False),
    ],
)
def test_accept_negotiation(accept, json):
    assert wants_json(accept) is json
