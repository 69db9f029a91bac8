"""Where the repository and the data the tests carry (`tests/data`) are, and how to load it."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"


def data_path(*parts: str) -> Path:
    """A file under `tests/data` (see its README); a failure when it is missing."""
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.fail(f"{path} is missing: the repository carries it in tests/data")
    return path


def load_vectors(name: str) -> dict:
    """A test-vector file of `tests/data`, with its float16-stored `state_dict` and `input` upcast
    to float32 (exactly the weights and input its logits were computed from)."""
    import torch

    vectors = torch.load(data_path(name), weights_only=False)
    vectors["state_dict"] = {
        k: v.float() if v.is_floating_point() else v for k, v in vectors["state_dict"].items()
    }
    vectors["input"] = vectors["input"].float()
    return vectors
