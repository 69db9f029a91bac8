"""Loading a benchmark script as a module, to test its functions: the script's own folder is
importable while it loads (its helpers are siblings), and nothing stays on `sys.path` after."""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType

from tests.support.paths import REPO


def load_benchmark(name: str) -> ModuleType:
    """`benchmarks/<name>.py` as a module named `benchmarks_<name>`."""
    folder = str(REPO / "benchmarks")
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", f"{folder}/{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    sys.path.insert(0, folder)
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(folder)
    return module
