"""The optional extras of the distribution, and the one-line error of a feature whose extra is missing.

`pip install rangeret-service` is the library and its light commands (numpy, torch, PyYAML, tqdm,
matplotlib). Ray, the HTTP gateway, ONNX and the model hub are extras (`pip install
'rangeret-service[ray]'`, ...; `all` holds every one). A feature that needs an extra checks for
its modules before importing any of them, and without them raises `MissingExtraError`, whose
message is the line to show. Imports nothing of the project but `rangeret.exceptions`.
"""

from __future__ import annotations

import importlib.util

from rangeret.exceptions import DISTRIBUTION, MissingExtraError

__all__ = ["DISTRIBUTION", "EXTRA_MODULES", "MissingExtraError", "extra_installed", "require_extra"]

#: The modules each optional extra of the distribution provides (pyproject.toml's
#: `[project.optional-dependencies]`): a feature runs only when all of its extra's are importable.
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "ray": ("ray",),
    "gateway": (
        "fastapi",
        "starlette",
        "uvicorn",
        "pydantic",
        "pydantic_settings",
        "python_multipart",
        "httpx",
        "prometheus_client",
    ),
    "onnx": ("onnx", "onnxscript", "onnxruntime"),
    "hub": ("huggingface_hub",),
    "files": ("pypcd4", "laspy", "lazrs"),
    "bags": ("rosbags",),
    "ros2": ("rclpy", "sensor_msgs", "diagnostic_msgs"),
}


def extra_installed(extra: str) -> bool:
    """Whether every module of `extra` (a key of `EXTRA_MODULES`) can be imported here."""
    return all(_importable(name) for name in EXTRA_MODULES[extra])


def require_extra(feature: str, extra: str) -> None:
    """Raise `MissingExtraError` for `feature` (what the user asked for, e.g. `rangeret serve`)
    unless `extra` is installed; checked before the feature imports any of its modules."""
    if not extra_installed(extra):
        raise MissingExtraError(feature, extra)


def _importable(name: str) -> bool:
    """Whether module `name` can be found, without importing it."""
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False
