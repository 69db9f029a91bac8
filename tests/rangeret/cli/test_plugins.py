"""Subcommands contributed by the Ray and HTTP layers through entry points."""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys

from rangeret import plugins
from rangeret.cli.main import BUILTIN_COMMANDS, build_parser, subcommands
from rangeret.plugins import COMMANDS_GROUP, TRAIN_BACKENDS_GROUP, Subcommand, load_plugins


def test_the_layers_contribute_serve_demo_and_train_on_ray():
    names = [c.name for c in subcommands()]
    assert names[: len(BUILTIN_COMMANDS)] == [c.name for c in BUILTIN_COMMANDS]
    assert {"serve", "demo"} <= set(names) and len(names) == len(set(names))
    assert [type(b).__name__ for b in load_plugins(TRAIN_BACKENDS_GROUP)] == ["TrainBackend"]
    args = build_parser("train").parse_args(
        ["train", "--dataset", "d", "--model", "rangeret-thesis", "--out", "o", "--ray"]
    )
    assert args.ray and args.workers == 2
    args = build_parser("serve").parse_args(["serve", "--port", "8123", "--no-knn"])
    assert args.port == 8123 and args.knn is False


def test_light_commands_load_no_torch_ray_or_web_stack():
    code = (
        "import sys; from rangeret.cli.main import build_parser; "
        "build_parser('evaluate').parse_args(['evaluate', '--dataset', 'd', '--predictions', 'p', "
        "'--split', 'valid']); "
        "print(sorted(m for m in ('torch', 'ray', 'fastapi', 'uvicorn') if m in sys.modules))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "[]"


class _BrokenEntryPoint:
    name, value = "broken", "nowhere:THING"

    def load(self):
        raise ImportError("No module named 'nowhere'")


class _GoodEntryPoint:
    name, value = "good", "here:THING"

    def load(self):
        return Subcommand("good", "works", lambda p: None, lambda a: 0)


def test_a_broken_plugin_is_logged_and_left_out(monkeypatch, caplog):
    monkeypatch.setattr(
        plugins, "entry_points", lambda group: [_GoodEntryPoint(), _BrokenEntryPoint()]
    )
    with caplog.at_level(logging.WARNING, logger="rangeret.plugins"):
        found = load_plugins(COMMANDS_GROUP)
    assert [c.name for c in found] == ["good"]
    assert "cannot load broken" in caplog.text and "nowhere" in caplog.text


def test_every_builtin_subcommand_parses_its_own_options():
    parser = build_parser(None)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        options = [a for a in p._actions if a.dest != "help"]
        assert len(options) > 2, name


def test_each_builtin_command_is_registered_by_its_own_module():
    """Every library subcommand's options and body live in the module of `rangeret.cli` named
    after it (`validate-submission` beside `submission`)."""
    modules = {c.name: {c.add_arguments.__module__, c.run.__module__} for c in BUILTIN_COMMANDS}
    assert modules["validate-submission"] == {"rangeret.cli.submission"}
    assert modules["train"] == {"rangeret.cli.main"}  # imports rangeret.cli.train when used
    for name, found in modules.items():
        if name not in ("validate-submission", "train"):
            assert found == {f"rangeret.cli.{name}"}, name
