"""The library's long-standing public paths keep working with their signatures and defaults,
wherever the code behind them lives."""

from __future__ import annotations

import inspect

import numpy as np


def _defaults(func) -> dict[str, object]:
    return {
        name: p.default
        for name, p in inspect.signature(func).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


def test_scan_reading_keeps_its_path():
    from rangeret.io import ScanFormatError, read_scan

    assert issubclass(ScanFormatError, ValueError)
    assert next(iter(inspect.signature(read_scan).parameters)) == "path"


def test_projection_keeps_its_path_and_defaults():
    from rangeret.projection import project

    assert list(inspect.signature(project).parameters)[:5] == [
        "points",
        "height",
        "width",
        "fov_up",
        "fov_down",
    ]
    defaults = _defaults(project)
    assert {k: defaults[k] for k in ("height", "width", "fov_up", "fov_down")} == {
        "height": 64,
        "width": 1024,
        "fov_up": 3.0,
        "fov_down": -25.0,
    }
    points = np.array([[10.0, 0.0, 0.0, 0.5], [0.0, 5.0, -1.0, 0.2]], dtype=np.float32)
    p = project(points)
    assert p.image.shape == (5, 64, 1024) and p.mask.shape == (64, 1024)
    assert p.proj_x.dtype == np.int64 and p.unproj_range.shape == (2,)


def test_knn_refine_keeps_its_path_and_defaults():
    from rangeret.knn import refine

    names = ["proj_range", "unproj_range", "proj_argmax", "proj_x", "proj_y"]
    assert list(inspect.signature(refine).parameters)[:10] == [
        *names,
        "k",
        "search",
        "sigma",
        "cutoff",
        "num_classes",
    ]
    defaults = _defaults(refine)
    assert {k: defaults[k] for k in ("k", "search", "sigma", "cutoff", "num_classes")} == {
        "k": 7,
        "search": 7,
        "sigma": 1.0,
        "cutoff": 1.0,
        "num_classes": 20,
    }


def test_models_keep_their_paths():
    from rangeret.models import build_model, load_checkpoint

    assert list(inspect.signature(build_model).parameters)[:4] == [
        "name",
        "height",
        "width",
        "num_classes",
    ]
    assert _defaults(build_model) == {"height": 64, "width": 1024, "num_classes": 20}
    assert list(inspect.signature(load_checkpoint).parameters)[:4] == [
        "path",
        "model",
        "height",
        "width",
    ]
