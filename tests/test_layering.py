"""The layers depend one way, rangeret <- workers <- service (and rangeret <- ros2node, the
ROS 2 node beside them), checked on every source file.

Every import counts: at module level, inside functions, under TYPE_CHECKING, and modules named
to `importlib.import_module`. A test fixture checks that the checker itself sees each kind.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.support.paths import REPO

PACKAGES = ("rangeret", "workers", "service", "ros2node")
#: ROS 2's own modules, which only the node imports.
ROS_MODULES = ("rclpy", "sensor_msgs", "diagnostic_msgs", "std_msgs", "builtin_interfaces")


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
            if not within(module, "ros2node") and any(
                within(target, m) for m in ("ros2node", *ROS_MODULES)
            ):
                found.append(f"{module} imports {target}")
            if within(module, "ros2node") and (
                within(target, "workers") or within(target, "service")
            ):
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
        "import importlib\nimportlib.import_module('workers.stages')\n",
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


# --- no silent SemanticKITTI fallbacks ------------------------------------------------------------

#: Files that may name SemanticKITTI's built-ins as a default, each with why.
FALLBACK_ALLOWED = {
    "rangeret/options.py": "the command line is where the default profile applies",
    "rangeret/cli/": "the command line is where the default profile applies",
    "rangeret/dataset/profiles.py": "defines the built-in profiles and the default one",
    "rangeret/dataset/labels.py": "defines the bundled SemanticKITTI label configuration",
    "service/settings.py": "the gateway's settings are where the default profile applies",
    "service/server.py": "the gateway's settings are where the default profile applies",
    "rangeret/sim/classes.py": "the simulated scenes are labelled with SemanticKITTI's raw ids",
}
#: Public contract functions (DESIGN section 7) whose documented short form keeps a default.
CONTRACT_DEFAULTS = {
    ("rangeret/io/scans.py", "read_scan"): "`rangeret.io.read_scan(path)` -> float32 (N, 4)",
}
#: Parameter defaults that would bypass a profile.
FALLBACK_NAMES = ("KITTI_RECORD", "KITTI_LAYOUT")


def _name(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def fallbacks(source: str) -> list[tuple[int, str, str | None]]:
    """(line, what, enclosing function) of every profile fallback in `source`: a parameter
    defaulting to SemanticKITTI's record or layout, a `load_profile(None)`, `load_profile()` or
    `semantickitti()` call, and a `read_scan` call that does not pass its record."""
    found: list[tuple[int, str, str | None]] = []

    def visit(node: ast.AST, function: str | None) -> None:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            defaults = [*node.args.defaults, *(d for d in node.args.kw_defaults if d is not None)]
            for default in defaults:
                if _name(default) in FALLBACK_NAMES:
                    found.append((default.lineno, f"a {_name(default)} default", node.name))
            function = node.name
        if isinstance(node, ast.Call):
            called = _name(node.func)
            plain = not node.args or (
                isinstance(node.args[0], ast.Constant) and node.args[0].value is None
            )
            if called == "load_profile" and plain and not node.keywords:
                found.append((node.lineno, "load_profile(None)", function))
            elif called == "semantickitti" and not node.args:
                found.append((node.lineno, "semantickitti()", function))
            elif (
                called == "read_scan"
                and len(node.args) < 2
                and "record" not in {k.arg for k in node.keywords}
            ):
                found.append((node.lineno, "read_scan without its record", function))
        for child in ast.iter_child_nodes(node):
            visit(child, function)

    visit(ast.parse(source), None)
    return found


def test_the_fallback_checker_sees_each_kind():
    source = (
        "def a(record=KITTI_RECORD): ...\n"
        "def b(*, layout=io.KITTI_LAYOUT): ...\n"
        "def c():\n"
        "    load_profile(None); load_profile(); semantickitti(); read_scan(p)\n"
        "    load_profile('pandaset'); read_scan(p, record=r); read_scan(p, r)\n"
    )
    assert [(line, what) for line, what, _ in fallbacks(source)] == [
        (1, "a KITTI_RECORD default"),
        (2, "a KITTI_LAYOUT default"),
        (4, "load_profile(None)"),
        (4, "load_profile(None)"),
        (4, "semantickitti()"),
        (4, "read_scan without its record"),
    ]


def test_no_silent_semantickitti_fallbacks():
    """Profiles, point records, layouts and label configurations are passed explicitly inside
    the library and the service; the default profile applies only at the edges allowed above."""
    found = []
    for package in ("rangeret", "workers", "service"):
        for path in sorted((REPO / package).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            if any(rel == a or (a.endswith("/") and rel.startswith(a)) for a in FALLBACK_ALLOWED):
                continue
            for line, what, function in fallbacks(path.read_text()):
                if (rel, function) not in CONTRACT_DEFAULTS:
                    found.append(f"{rel}:{line}: {what} in {function or 'the module'}")
    assert found == []
