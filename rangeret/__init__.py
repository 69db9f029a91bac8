"""RangeRet: range-image LiDAR semantic segmentation with Retentive Networks.

A plain library (numpy and torch): scan I/O, projection, models, kNN refinement, metrics and
SemanticKITTI submissions. `workers/` runs it on Ray and `service/` serves it over HTTP.
"""

import importlib
from collections.abc import Callable, Mapping
from pathlib import Path

__version__ = "0.1.0"

#: The files the package ships: demo weights, the model registry, profiles and label configurations.
DATA_DIR = Path(__file__).with_name("data")


def lazy_exports(package: str, exports: Mapping[str, str]) -> Callable[[str], object]:
    """A package's `__getattr__` that imports each of `exports` (name -> module) on first use,
    so that importing the package costs no more than its own module."""
    namespace = importlib.import_module(package).__dict__

    def getattr_(name: str) -> object:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(exports[name]), name)
        namespace[name] = value
        return value

    return getattr_
