"""Only the registry, the layouts and the profile parser choose by a benchmark's, a layout's, a
scoring's or a profile's name or type; every other module asks them.

An AST scan of `rangeret/`, `service/` and `workers/` finds comparisons of such a name (an
attribute `kind` or `scoring`, or the `name` of a profile, benchmark or layout) with a string or
an upper-case constant, and `isinstance` tests against a dataset layout class. A fixture checks
that the scan sees each form; another counts the modules that take the loose `version` keyword.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.support.paths import REPO

PACKAGES = ("rangeret", "service", "workers")
#: The modules that own the choice: the benchmark registry, the layouts, the profile parser.
OWNERS = {
    "rangeret/submission/benchmarks.py",
    "rangeret/dataset/layout.py",
    "rangeret/dataset/table_layout.py",
    "rangeret/dataset/profiles.py",
}
#: The nuScenes table modules, where a version is what they read.
NUSCENES_MODULES = {
    "rangeret/dataset/nuscenes_tables.py",
    "rangeret/dataset/table_layout.py",
    "rangeret/submission/nuscenes.py",
    "rangeret/sim/nuscenes_tree.py",
    "rangeret/dataset/table_upload_rules.py",
}
LAYOUT_CLASSES = {"SequenceLayout", "TableLayout", "DatasetLayout"}
NAME_OWNERS = ("profile", "benchmark", "layout")


def _chain(node: ast.AST) -> list[str]:
    """The dotted names of an attribute chain, outermost last (`a.b.c` -> [a, b, c])."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        parts.append(node.id)
    return parts[::-1]


def _is_name_of_choice(node: ast.AST) -> bool:
    chain = _chain(node)
    if len(chain) < 2:
        return False
    if chain[-1] == "scoring":
        return True
    owned = any(owner in part.lower() for part in chain[:-1] for owner in NAME_OWNERS)
    if chain[-1] == "kind":  # a layout's kind (a dtype's is not one)
        return any("layout" in part.lower() for part in chain[:-1])
    return chain[-1] == "name" and owned


def _is_constant(node: ast.AST) -> bool:
    if isinstance(node, ast.Constant):
        return isinstance(node.value, str)
    if isinstance(node, ast.Name):
        return node.id.isupper() and len(node.id) > 1
    if isinstance(node, ast.Attribute):
        return node.attr.isupper() and len(node.attr) > 1
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return bool(node.elts) and all(_is_constant(e) for e in node.elts)
    return False


def choices(source: str) -> list[int]:
    """Lines of the source that choose by a name or a layout type."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any(_is_name_of_choice(s) for s in sides) and any(_is_constant(s) for s in sides):
                found.append(node.lineno)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == "isinstance"
            and len(node.args) == 2
        ):
            kinds = node.args[1]
            names = kinds.elts if isinstance(kinds, ast.Tuple) else [kinds]
            if any(_chain(n)[-1:] and _chain(n)[-1] in LAYOUT_CLASSES for n in names):
                found.append(node.lineno)
    return found


def source_files() -> dict[str, Path]:
    return {
        str(path.relative_to(REPO)): path
        for package in PACKAGES
        for path in sorted((REPO / package).rglob("*.py"))
    }


@pytest.mark.parametrize(
    "source",
    [
        'if profile.layout.kind == "tables":\n    pass',
        "x = layout.kind != KIND",
        'if self.scoring == "nuscenes":\n    pass',
        'if profile.name == "semantickitti":\n    pass',
        "ok = model.profile.name in (DEFAULT_PROFILE, 'nuscenes')",
        "benchmark = profile.name == BENCHMARK_PROFILE",
        "isinstance(profile.layout, TableLayout)",
        "isinstance(layout, (int, layouts.SequenceLayout))",
    ],
)
def test_the_scan_sees_each_form_of_choice(source):
    assert choices(source) == [1]


@pytest.mark.parametrize(
    "source",
    [
        "if gt.dtype.kind == 'i':\n    pass",  # a dtype's kind is no layout's
        "same = request.profile != profile.name",  # two names compared, not a constant
        "if profile.layout.folders is None:\n    pass",  # a capability, asked of the layout
        "isinstance(value, bool)",
    ],
)
def test_the_scan_leaves_what_is_not_a_choice(source):
    assert choices(source) == []


def test_only_the_registry_the_layouts_and_the_profile_parser_choose():
    sites = {
        name: lines for name, path in source_files().items() if (lines := choices(path.read_text()))
    }
    outside = {name: lines for name, lines in sites.items() if name not in OWNERS}
    assert outside == {}
    assert sum(len(lines) for lines in sites.values()) <= 6 and len(sites) <= 3


def test_few_signatures_outside_the_table_modules_take_a_version():
    found = []
    for name, path in source_files().items():
        if name in NUSCENES_MODULES or name in OWNERS:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                args = node.args
                every = [*args.posonlyargs, *args.args, *args.kwonlyargs]
                if any(a.arg == "version" for a in every):
                    found.append(f"{name}:{node.lineno} {node.name}")
    assert len(found) <= 6, found
