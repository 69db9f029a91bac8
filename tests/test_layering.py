"""The layers depend one way, rangeret <- workers <- service, checked on every source file.

Every import counts: at module level, inside functions, under TYPE_CHECKING, and modules named
to `importlib.import_module`. A test fixture checks that the checker itself sees each kind.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.support.paths import REPO

PACKAGES = ("rangeret", "workers", "service")


def imported_modules(source: str, module: str) -> set[str]:
    """Every module the source of `module` imports, by its full dotted name."""
    found: set[str] = set()
    package = module.rsplit(".", 1)[0] if "." in module else module
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")
                parent = parent[: len(parent) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
        elif (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            found.add(node.args[0].value)
    return found


def source_files() -> dict[str, Path]:
    """Module name -> file of every source file of the three packages."""
    files = {}
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            files[".".join(parts)] = path
    return files


def within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def violations() -> list[str]:
    """Every import that points against the layering, as 'module imports target'."""
    found = []
    for module, path in source_files().items():
        for target in sorted(imported_modules(path.read_text(), module)):
            if within(module, "rangeret") and (
                within(target, "workers") or within(target, "service")
            ):
                found.append(f"{module} imports {target}")
            if within(module, "workers") and within(target, "service"):
                found.append(f"{module} imports {target}")
            if not within(module, "rangeret.cli") and within(target, "rangeret.cli"):
                found.append(f"{module} imports {target}")
    return found


def test_layers_depend_one_way():
    assert violations() == []


def test_every_package_has_sources():
    modules = source_files()
    for package in PACKAGES:
        assert package in modules and sum(within(m, package) for m in modules) > 3


@pytest.mark.parametrize(
    "source",
    [
        "import workers.pipeline",
        "from service import app",
        "def f():\n    from workers.demo import run_demo\n",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import service.settings\n",
        "import importlib\nimportlib.import_module('workers.scans')\n",
    ],
)
def test_the_checker_sees_every_kind_of_import(source):
    targets = imported_modules(source, "rangeret.example")
    assert any(within(t, "workers") or within(t, "service") for t in targets)


def test_the_checker_resolves_relative_imports():
    assert "rangeret.models.blocks.decay" in imported_modules(
        "from .decay import x", "rangeret.models.blocks.retention"
    )
    assert "rangeret.cli" in imported_modules(
        "from ... import cli", "rangeret.models.blocks.retention"
    )


def test_no_import_cycles_between_modules():
    """No two project modules import each other, directly or through others."""
    modules = source_files()
    graph = {
        m: {
            t
            for t in imported_modules(p.read_text(), m)
            if t in modules and t != m and not within(m, t)
        }
        for m, p in modules.items()
    }
    cycles = []
    state: dict[str, int] = {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join([*stack[stack.index(nxt) :], nxt]))
            elif nxt not in state:
                visit(nxt, [*stack, nxt])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert cycles == []


def test_no_source_file_is_longer_than_500_lines():
    """Small modules, one concept each: a file that grows past 500 lines is split along its jobs."""
    long = {
        module: n
        for module, path in source_files().items()
        if (n := len(path.read_text().splitlines())) > 500
    }
    assert long == {}


def test_the_library_top_level_holds_few_modules():
    """`rangeret/` keeps its concepts in subpackages; at most 8 modules sit beside `__init__.py`."""
    top = sorted(p.name for p in (REPO / "rangeret").glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 8, top
