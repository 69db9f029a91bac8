"""Run the official nuScenes devkit on a tree and print one JSON object; see tests/support/devkit.py.

Run BY the devkit venv's python, so it imports only the devkit, numpy and the standard library
(never the project). Everything the devkit prints goes to stderr; stdout carries the JSON alone.

    evaluate --dataroot ROOT --version VERSION --results FOLDER --eval-set SPLIT
        {"miou": ..., "freq_weighted_iou": ..., "iou_per_class": {name: value or null}}
    validate --dataroot ROOT --version VERSION --results FOLDER --eval-set SPLIT
        {"ok": true} or {"ok": false, "error": "AssertionError: ..."} (exit 0 both ways)
    load --dataroot ROOT --version VERSION
        {"scenes": [names], "samples": n, "lidarseg": n, "categories": {index: name},
         "panoptic": n, "first_panoptic": null or {"filename", "dtype", "points",
         "semantic_is_lidarseg", "sha256"} (its values as `load_bin_file` reads them)}
    panoptic-arrays --input FILE.npz
        the devkit's PanopticEval (its nuScenes settings) over the scans of FILE.npz: `scans`,
        `pred_class_K`, `pred_instance_K`, `gt_class_K`, `gt_instance_K` for K < scans, and
        optionally `min_points` (15 otherwise); {"tp", "fp", "fn", "iou_sum", "confusion",
        "pq", "sq", "rq", "iou" (per class), "mean_pq", "mean_sq", "mean_rq", "mean_iou",
        "results" (the dict NuScenesPanopticEval wraps those in)}
    panoptic-evaluate --dataroot ROOT --version VERSION --results FOLDER --eval-set SPLIT
                      [--min-inst-points N]
        NuScenesPanopticEval's segmentation results as it writes them: {"all": {"PQ", "SQ",
        "RQ", "mIoU", "PQ_dagger"}, class name: {"PQ", "SQ", "RQ", "IoU"}, ...}, NaN as null

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
    """What the devkit loads from the tree: scene names, table sizes, and the first panoptic
    file as the devkit's own loader reads it."""
    import hashlib

    from nuscenes.utils.data_io import load_bin_file, panoptic_to_lidarseg

    nusc = load_nusc(args)
    categories = getattr(nusc, "lidarseg_idx2name_mapping", {})
    panoptic = getattr(nusc, "panoptic", [])
    first = None
    if panoptic:
        record = panoptic[0]
        values = load_bin_file(os.path.join(nusc.dataroot, record["filename"]), type="panoptic")
        lidarseg = nusc.get("lidarseg", record["token"])["filename"]
        labels = load_bin_file(os.path.join(nusc.dataroot, lidarseg), type="lidarseg")
        first = {
            "filename": record["filename"],
            "dtype": str(values.dtype),
            "points": len(values),
            "semantic_is_lidarseg": bool((panoptic_to_lidarseg(values) == labels).all()),
            "sha256": hashlib.sha256(values.astype("<u2").tobytes()).hexdigest(),
        }
    return {
        "scenes": [scene["name"] for scene in nusc.scene],
        "samples": len(nusc.sample),
        "lidarseg": len(getattr(nusc, "lidarseg", [])),
        "categories": {str(k): v for k, v in sorted(categories.items())},
        "panoptic": len(panoptic),
        "first_panoptic": first,
    }


def nan_free(value: Any) -> Any:
    """A JSON value with every NaN float replaced by None, through dicts and lists."""
    if isinstance(value, dict):
        return {k: nan_free(v) for k, v in value.items()}
    if isinstance(value, list):
        return [nan_free(v) for v in value]
    if isinstance(value, float) and math.isnan(value):
        return None
    return value


def cmd_panoptic_arrays(args: argparse.Namespace) -> dict[str, Any]:
    """The devkit's PanopticEval, set up as NuScenesPanopticEval sets it up, over saved scans."""
    from types import SimpleNamespace

    import numpy as np
    from nuscenes.eval.panoptic.evaluate import NuScenesPanopticEval
    from nuscenes.eval.panoptic.panoptic_seg_evaluator import PanopticEval
    from nuscenes.eval.panoptic.utils import PanopticClassMapper

    # The class mapper's coarse classes, things and stuff need no NuScenes tables.
    mapper = PanopticClassMapper.__new__(PanopticClassMapper)
    mapper.ignore_class = mapper.get_ignore_class()
    coarse = mapper.get_coarse2idx()
    with np.load(args.input) as data:
        arrays = {k: data[k] for k in data.files}
    min_points = int(arrays["min_points"]) if "min_points" in arrays else 15
    evaluator = PanopticEval(
        n_classes=len(coarse), ignore=[mapper.ignore_class["index"]], min_points=min_points
    )
    for k in range(int(arrays["scans"])):
        evaluator.addBatch(
            arrays[f"pred_class_{k}"],
            arrays[f"pred_instance_{k}"],
            arrays[f"gt_class_{k}"],
            arrays[f"gt_instance_{k}"],
        )
    mean_pq, mean_sq, mean_rq, pq, sq, rq = evaluator.getPQ()
    mean_iou, iou = evaluator.getSemIoU()
    view = SimpleNamespace(
        id2name={idx: name for name, idx in coarse.items()},
        things=mapper.get_things().keys(),
        stuff=mapper.get_stuff().keys(),
    )
    results = NuScenesPanopticEval.wrap_result_segmentation(
        view, mean_pq, mean_sq, mean_rq, mean_iou, pq, sq, rq, iou
    )
    return nan_free(
        {
            "min_points": min_points,
            "tp": evaluator.pan_tp.tolist(),
            "fp": evaluator.pan_fp.tolist(),
            "fn": evaluator.pan_fn.tolist(),
            "iou_sum": evaluator.pan_iou.tolist(),
            "confusion": evaluator.px_iou_conf_matrix.tolist(),
            "pq": pq.tolist(),
            "sq": sq.tolist(),
            "rq": rq.tolist(),
            "iou": iou.tolist(),
            "mean_pq": float(mean_pq),
            "mean_sq": float(mean_sq),
            "mean_rq": float(mean_rq),
            "mean_iou": float(mean_iou),
            "results": json.loads(json.dumps(results)),
        }
    )


def cmd_panoptic_evaluate(args: argparse.Namespace) -> dict[str, Any]:
    """NuScenesPanopticEval (task segmentation) of `--results` on `--eval-set`, read back from the
    result file it writes."""
    import tempfile

    from nuscenes.eval.panoptic.evaluate import NuScenesPanopticEval

    nusc = load_nusc(args)
    with tempfile.TemporaryDirectory() as out_dir:
        NuScenesPanopticEval(
            nusc,
            results_folder=args.results,
            eval_set=args.eval_set,
            task="segmentation",
            min_inst_points=args.min_inst_points,
            out_dir=out_dir,
            verbose=False,
        ).evaluate()
        with open(os.path.join(out_dir, "segmentation-result.json")) as f:
            written = json.load(f)
    return nan_free(written["segmentation"])


def parser() -> argparse.ArgumentParser:
    """The command line: one subcommand per devkit entry point."""
    top = argparse.ArgumentParser(prog="devkit_check.py", description=__doc__.splitlines()[0])
    sub = top.add_subparsers(dest="command", required=True)
    commands: dict[str, tuple[Callable[[argparse.Namespace], dict[str, Any]], bool]] = {
        "evaluate": (cmd_evaluate, True),
        "validate": (cmd_validate, True),
        "load": (cmd_load, False),
        "panoptic-evaluate": (cmd_panoptic_evaluate, True),
    }
    for name, (func, needs_results) in commands.items():
        p = sub.add_parser(name, help=(func.__doc__ or "").strip())
        p.add_argument("--dataroot", required=True)
        p.add_argument("--version", required=True)
        if needs_results:
            p.add_argument("--results", required=True)
            p.add_argument("--eval-set", required=True)
        p.set_defaults(func=func)
    sub.choices["panoptic-evaluate"].add_argument("--min-inst-points", type=int, default=15)
    arrays = sub.add_parser("panoptic-arrays", help=(cmd_panoptic_arrays.__doc__ or "").strip())
    arrays.add_argument("--input", required=True)
    arrays.set_defaults(func=cmd_panoptic_arrays)
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
