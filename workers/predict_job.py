"""`python -m workers.predict_job`: predict a split on a Ray cluster, then report and archive.

    ray job submit --working-dir . -- python -m workers.predict_job --dataset /abs/ROOT \\
        --split test --out /abs/PRED --submission /abs/submission.zip --checkpoint rangeret-kitti-657

(the job runs in a copy of the working directory, so its paths are absolute: a relative one is
refused in one line, `workers.job_paths`).

Connects to the cluster in RAY_ADDRESS (set by `ray job submit`), or starts a local Ray when
none is set. On a multi-node cluster ROOT and PRED must be on storage every node mounts. The job
writes the predictions tree; for labelled scans the evaluation report (JSON and PNGs); with
`--submission` the validated archive. Scans already predicted are skipped (resume); the job
exits non-zero when any scan could not be predicted, naming each one. With `--panoptic` (or
`"panoptic": true` in `--inference-spec`) it writes the files `rangeret predict --panoptic` writes,
at the panoptic places of the layout, scores the labelled scans as `rangeret evaluate --panoptic`
does, and archives for the profile's panoptic benchmark. The run is added to PRED/run.json; a tree
holding predictions from other weights, or of the other task, is refused unless `--overwrite`. It
keeps its progress in PRED/progress.json (`workers.progress`): a record at the start, after
batches, and a final one at the very end, also when scans failed or bad input stopped it.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from rangeret.commands import CommandError, run_command
from rangeret.dataset.layout import ScanEntry, is_complete
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.selection import DatasetSelection
from rangeret.exceptions import RangeRetError
from rangeret.inference.loaded_weights import load_weights
from rangeret.inference.spec import InferenceSpec
from rangeret.inference.writing import check_outputs_apart
from rangeret.io.run_info import write_run_info
from rangeret.models.weights.demo import demo_warning, is_demo_checkpoint
from rangeret.options import (
    add_leaderboard_options,
    add_network_options,
    add_selection,
    leaderboard_from_args,
    selected_dataset,
)
from rangeret.submission.benchmark import ArchiveRequest
from rangeret.submission.benchmarks import benchmark_of, no_archive_reason
from rangeret.submission.leaderboard import description_text
from workers.cluster import connect
from workers.job_paths import check_job_paths
from workers.pipeline import describe_spec, run_pipeline
from workers.progress import ProgressWriter
from workers.sizing import PipelineOptions
from workers.stages import count_labels

log = logging.getLogger("workers.predict_job")


def build_parser() -> argparse.ArgumentParser:
    """Arguments of the job: the dataset selection, outputs, actors and the shared network options."""
    p = argparse.ArgumentParser(
        prog="python -m workers.predict_job", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    add_selection(
        p,
        partial_help="; also writes --submission as a partial archive (for tests only)",
    )
    p.add_argument(
        "--out", type=Path, required=True, metavar="PRED", help="predictions tree to write"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="predict every chosen scan again, replacing its prediction, also where PRED holds "
        "predictions from other weights (without it, scans already predicted are kept and a "
        "tree from other weights is refused); PRED/run.json lists every run",
    )
    p.add_argument(
        "--submission", type=Path, metavar="FILE.zip", help="also write the validated archive"
    )
    add_leaderboard_options(p.add_argument_group("leaderboard (description.txt of --submission)"))
    p.add_argument(
        "--report",
        type=Path,
        metavar="FILE.json",
        help="evaluation report of the labelled scans (PNGs beside it; with --panoptic the "
        "panoptic report, as `rangeret evaluate --panoptic --json` writes it, without PNGs)",
    )
    p.add_argument(
        "--actors",
        type=int,
        metavar="N",
        help="model actors (default: one per free GPU; on CPU clusters one per free CPU of a node)",
    )
    p.add_argument(
        "--read-cpus", type=float, default=0.25, help="CPU share of each read + project actor"
    )
    p.add_argument(
        "--read-roots",
        nargs="+",
        type=Path,
        metavar="DIR",
        help="read scans only from under these folders (links resolved when each scan is "
        "read); another scan is named as a failure (default: anywhere)",
    )
    p.add_argument(
        "--actor-cpus",
        type=float,
        metavar="N",
        help="CPUs of each CPU model actor (default: what readers and writers leave)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="less logging")
    add_network_options(p)
    p.add_argument(
        "--inference-spec",
        metavar="JSON",
        help="the network options as one JSON object by field name, as a gateway submits them "
        '(e.g. \'{"checkpoint": "/models/w.pt", "batch_size": 8}\'); not together with the '
        "network options above",
    )
    return p


def spec_of(args: argparse.Namespace) -> InferenceSpec:
    """The job's `InferenceSpec`: from --inference-spec when given (then no network option may
    be), else from the network options."""
    spec = InferenceSpec.from_args(args)
    if args.inference_spec is None:
        return spec
    if spec != InferenceSpec():
        given = ", ".join(sorted(spec.to_mapping()))
        raise CommandError(
            f"--inference-spec holds every network option: give {given} in it, not as options"
        )
    try:
        values = json.loads(args.inference_spec)
    except ValueError as exc:
        raise CommandError(f"--inference-spec is not JSON: {exc}") from exc
    except RecursionError:
        raise CommandError(
            "--inference-spec nests deeper than a JSON reader goes: it is one object of options"
        ) from None
    if not isinstance(values, dict):
        raise CommandError(f"--inference-spec must be a JSON object, got {type(values).__name__}")
    return InferenceSpec.from_mapping(values, where=" in --inference-spec")


def run(args: argparse.Namespace) -> int:
    """Run the job for parsed arguments; returns the exit code. The final progress record is
    written last, also when failed scans or bad input (the errors `run_command` reports as one
    line) end the job, except that input refused before the output folder exists leaves no folder
    behind; a job stopped by anything else leaves none."""
    check_job_paths(
        inputs=[("--dataset", args.dataset)],
        outputs=[("--out", args.out), ("--submission", args.submission), ("--report", args.report)],
    )
    recorder = ProgressWriter(args.out)
    existed = Path(args.out).is_dir()
    try:
        return _run(args, recorder)
    except RangeRetError as exc:
        if not recorder.finished and (existed or Path(args.out).is_dir()):
            try:
                recorder.finish(error=exc.reason if isinstance(exc, CommandError) else str(exc))
            except OSError as problem:  # the error itself is what the user must see
                log.warning("the final progress record could not be written: %s", problem)
        raise


def _run(args: argparse.Namespace, recorder: ProgressWriter) -> int:
    """The job's body, keeping its progress with `recorder`."""
    leaderboard = leaderboard_from_args(args)
    spec = spec_of(args)
    if args.actors is not None and args.actors < 1:
        raise CommandError(f"--actors must be at least 1, got {args.actors}")
    weights = load_weights(spec)
    if spec.backend == "onnxruntime" and spec.onnx is None:
        weights.export_onnx()  # once here, so that the model actors load it from the cache
    info, profile = weights.info, weights.profile
    if spec.panoptic and profile.panoptic_refusal() is not None:
        raise CommandError(str(profile.panoptic_refusal()))
    label_config = profile.labels
    selection = selected_dataset(args, profile, args.dataset, doing="predicting").for_task(
        spec.panoptic
    )
    sequences = list(selection.sequences)
    entries = selection.scans()
    complete = [
        not args.overwrite and is_complete(e, args.out, record=profile.points) for e in entries
    ]
    done = [e for e, finished in zip(entries, complete, strict=True) if finished]
    pending = [e for e, finished in zip(entries, complete, strict=True) if not finished]
    check_outputs_apart(pending, args.out)
    log.info(
        "%d scans in %s: %d to predict, %d already done",
        len(entries),
        ", ".join(sequences),
        len(pending),
        len(done),
    )
    demo = is_demo_checkpoint(info.sha256)
    write_run_info(
        args.out,
        describe_spec(spec, info, profile),
        runner="workers.predict_job",
        dataset=args.dataset,
        sequences=sequences,
        batch_size=spec.batch_size,
        overwrite=args.overwrite,
    )
    recorder.start(len(entries), len(done))

    connect(None)
    options = PipelineOptions(
        batch_size=spec.batch_size,
        actors=args.actors,
        read_cpus=args.read_cpus,
        actor_cpus=args.actor_cpus,
        use_gpu=None if spec.device == "auto" else spec.device == "cuda",
        read_roots=tuple(str(r.resolve()) for r in args.read_roots) if args.read_roots else None,
    )
    run = run_pipeline(
        spec,
        profile,
        pending,
        args.out,
        options,
        progress=recorder.batch,
        checkpoint_sha256=info.sha256,
    )
    precision = run.precision(spec)
    log.info("model actors: %s", run.actors_text())
    summary = replace(run.summary, total=len(entries), skipped=len(done))
    print(summary.text())

    if spec.panoptic:
        if summary.ok:
            _panoptic_report(args, selection, entries, profile, info.sha256, demo)
    else:
        evaluator = run.evaluator
        evaluator.merge(count_labels(done, args.out, profile))
        if evaluator.num_scans and summary.ok:
            report = evaluator.report(sequences, info.sha256)
            report.profile = profile.name
            report.precision = precision
            report.backend = spec.backend
            if demo:
                report.notes.append(demo_warning(profile.name))
            print(report.table())
            if args.report:
                from rangeret.evaluation.plots import write_plots

                report.write_json(args.report)
                plots = write_plots(
                    report, args.report.with_name(args.report.stem + "-plots"), config=label_config
                )
                print(f"report: {args.report}; plots: {', '.join(map(str, plots))}")
        elif args.report and not evaluator.num_scans:
            log.warning(
                "no scan of %s has ground truth: no evaluation report", ", ".join(sequences)
            )

    if not summary.ok:
        recorder.finish(failures=summary.failed, precision=precision)
        summary.raise_failures(args.out)
    if args.submission:
        reason = no_archive_reason(profile, panoptic=spec.panoptic)
        if reason is not None:
            raise CommandError(f"{reason}; every prediction was written")
        request = ArchiveRequest(
            args.submission,
            args.dataset,
            profile,
            selection.archive_options(),
            allow_partial=args.allow_partial,
            progress=not args.quiet,
            predictions=args.out,
            description=description_text(
                leaderboard,
                written_by="workers.predict_job",
                checkpoint_sha256=info.sha256,
                model=info.name,
                profile=profile.name,
                demo_weights=demo,
            ),
            leaderboard=leaderboard,
            checkpoint_sha256=info.sha256,
        )
        check = benchmark_of(profile, panoptic=spec.panoptic).write_archive(request)
        print(check.summary())
    recorder.finish(precision=precision)
    return 0


def _panoptic_report(
    args: argparse.Namespace,
    selection: DatasetSelection,
    entries: Sequence[ScanEntry],
    profile: DatasetProfile,
    sha256: str,
    demo: bool,
) -> None:
    """The panoptic scores of the sequences whose scans all have panoptic ground truth, read
    back from the tree as `rangeret evaluate --panoptic` reads it, under the profile's panoptic
    benchmark's rules: printed, and written to --report."""
    from rangeret.evaluation.panoptic_evaluate import evaluate_panoptic

    truth: dict[str, list[bool]] = {}
    for entry in entries:
        truth.setdefault(entry.sequence, []).append(entry.label_path is not None)
    labelled = [seq for seq, found in truth.items() if all(found)]
    partly = [seq for seq, found in truth.items() if any(found) and not all(found)]
    if partly:
        log.warning(
            "sequences %s have panoptic ground truth for some scans only: left out of the report",
            ", ".join(partly),
        )
    if not labelled:
        if args.report:
            log.warning(
                "no sequence of %s has panoptic ground truth: no evaluation report",
                ", ".join(selection.sequences),
            )
        return
    benchmark = benchmark_of(profile, panoptic=True)
    if benchmark.panoptic_rules is None:
        log.warning(
            "the %s profile names no panoptic benchmark to score by: no evaluation report",
            profile.name,
        )
        return
    report = evaluate_panoptic(
        selection.only(labelled),
        args.out,
        profile=profile,
        rules=benchmark.panoptic_rules,
        benchmark=benchmark.name,
        checkpoint_sha256=sha256,
    )
    print(report.table())
    if demo:
        print(f"Note: {demo_warning(profile.name)}.")
    if args.report:
        report.write_json(args.report)
        print(f"report: {args.report}")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: parse, run, and turn input errors into one-line messages and exit code 1."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING if args.quiet else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return run_command("predict_job", run, args)


if __name__ == "__main__":
    sys.exit(main())
