"""Run the official nuScenes devkit on a tree and print one JSON object; see tests/support/devkit.py.

Run BY the devkit venv's python, so it imports only the devkit, numpy and the standard library
(never the project). Everything the devkit prints goes to stderr; stdout carries the JSON alone.

    evaluate --dataroot ROOT --version VERSION --results FOLDER --eval-set SPLIT
        {"miou": ..., "freq_weighted_iou": ..., "iou_per_class": {name: value or null}}
    validate --dataroot ROOT --version VERSION --results FOLDER --eval-set SPLIT
        {"ok": true} or {"ok": false, "error": "AssertionError: ..."} (exit 0 both ways)
    load --dataroot ROOT --version VERSION
        {"scenes": [names], "samples": n, "lidarseg": n, "categories": {index: name}}

Any other failure (a tree the devkit cannot load, a crash) exits 1 with the traceback and a last
line `devkit_check.py: error: TYPE: MESSAGE` on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import traceback
from collections.abc import Callable, Iterator
from typing import Any

# This script sits next to tests/support/nuscenes.py (the project's fixtures), which would shadow
# the devkit's `nuscenes` package if the script's folder were on sys.path (as it is without -I).
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]


@contextlib.contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """Send everything written to stdout, by Python or by C code on fd 1, to stderr meanwhile."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def nan_to_none(value: Any) -> float | None:
    """A metric as a float, NaN as None (JSON null)."""
    value = float(value)
    return None if math.isnan(value) else value


def load_nusc(args: argparse.Namespace) -> Any:
    """The devkit's NuScenes object for `--version` under `--dataroot`."""
    from nuscenes import NuScenes

    return NuScenes(version=args.version, dataroot=args.dataroot, verbose=False)


def cmd_evaluate(args: argparse.Namespace) -> dict[str, Any]:
    """The devkit's lidarseg evaluation of `--results` on `--eval-set`."""
    from nuscenes.eval.lidarseg.evaluate import LidarSegEval

    nusc = load_nusc(args)
    results = LidarSegEval(nusc, args.results, args.eval_set, verbose=False).evaluate()
    return {
        "miou": nan_to_none(results["miou"]),
        "freq_weighted_iou": nan_to_none(results["freq_weighted_iou"]),
        "iou_per_class": {str(k): nan_to_none(v) for k, v in results["iou_per_class"].items()},
    }


def cmd_validate(args: argparse.Namespace) -> dict[str, Any]:
    """The devkit's submission check of `--results` on `--eval-set`: ok, or its error."""
    from nuscenes.eval.lidarseg.validate_submission import validate_submission

    nusc = load_nusc(args)  # a tree that does not load is a failure of the run, not a rejection
    try:
        validate_submission(nusc, args.results, args.eval_set, verbose=False)
    except Exception as exc:
        traceback.print_exc()
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
    return {"ok": True}


def cmd_load(args: argparse.Namespace) -> dict[str, Any]:
    """What the devkit loads from the tree: scene names and table sizes."""
    nusc = load_nusc(args)
    categories = getattr(nusc, "lidarseg_idx2name_mapping", {})
    return {
        "scenes": [scene["name"] for scene in nusc.scene],
        "samples": len(nusc.sample),
        "lidarseg": len(getattr(nusc, "lidarseg", [])),
        "categories": {str(k): v for k, v in sorted(categories.items())},
    }


def parser() -> argparse.ArgumentParser:
    """The command line: one subcommand per devkit entry point."""
    top = argparse.ArgumentParser(prog="devkit_check.py", description=__doc__.splitlines()[0])
    sub = top.add_subparsers(dest="command", required=True)
    commands: dict[str, tuple[Callable[[argparse.Namespace], dict[str, Any]], bool]] = {
        "evaluate": (cmd_evaluate, True),
        "validate": (cmd_validate, True),
        "load": (cmd_load, False),
    }
    for name, (func, needs_results) in commands.items():
        p = sub.add_parser(name, help=(func.__doc__ or "").strip())
        p.add_argument("--dataroot", required=True)
        p.add_argument("--version", required=True)
        if needs_results:
            p.add_argument("--results", required=True)
            p.add_argument("--eval-set", required=True)
        p.set_defaults(func=func)
    return top


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand and print its JSON on stdout; 1 with the error on stderr on failure."""
    args = parser().parse_args(argv)
    try:
        with stdout_to_stderr():
            result = args.func(args)
    except Exception as exc:
        traceback.print_exc()
        print(f"devkit_check.py: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(result, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
