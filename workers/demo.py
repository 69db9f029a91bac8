"""`rangeret demo`: the whole service on simulated scans, in a few minutes on a laptop.

It simulates a small dataset in the SemanticKITTI layout (a labelled validation sequence 08 and
short unlabelled test sequences 11 to 21), starts a local Ray, predicts every scan through the
workers' pipeline with the bundled demo weights, evaluates the validation sequence (table, JSON,
PNGs), writes and validates a partial submission archive, and renders one range image with its
ground truth and prediction. The predictions tree gets its `run.json` like every other runner's.
With `--profile nuscenes` the dataset is a simulated v1.0-mini tree (both mini_val scenes, with
labels), evaluated as the devkit scores it, and the archive is the mini_val results folder,
whole and validated. With `--panoptic` the same path finds objects too: the pipeline writes the
panoptic labels `rangeret predict --panoptic` writes, the report is the panoptic benchmark's
(`rangeret evaluate --panoptic`: PQ, SQ, RQ, PQ-dagger and IoU), printed with PQ beside mIoU,
and the archive is the panoptic benchmark's. The demo weights were trained on simulated scenes
only.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np

from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.projection import project_with
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.evaluate import evaluate_predictions
from rangeret.evaluation.metrics import EvaluationReport
from rangeret.evaluation.panoptic_evaluate import PanopticReport, evaluate_panoptic
from rangeret.evaluation.plots import plot_range_image, write_plots
from rangeret.exceptions import InputError
from rangeret.inference.loaded_weights import load_weights
from rangeret.inference.spec import InferenceSpec
from rangeret.io.run_info import check_weights, write_run_info
from rangeret.io.scans import read_scan
from rangeret.models.weights.demo import demo_checkpoint, demo_warning, is_demo_path
from rangeret.sim.trees import simulate_tree
from rangeret.submission.benchmark import ArchiveRequest, Benchmark
from rangeret.submission.benchmarks import benchmark_of
from rangeret.submission.leaderboard import LeaderboardEntry, description_text
from workers.cluster import session_folder, start_local
from workers.pipeline import describe_spec, run_pipeline
from workers.ray_files import TOKEN_FILE, keep_logs, run_token
from workers.sizing import PipelineOptions

log = logging.getLogger(__name__)

#: What the panoptic demo adds to its benchmark's lines on running the same on real data.
PANOPTIC_HINT = (
    "For panoptic segmentation add --panoptic to predict, evaluate and the Ray job, and "
    "--task panoptic to submission and validate-submission."
)


def run_demo(
    out: Path | str | None = None,
    valid_scans: int = 8,
    test_scans: int = 1,
    checkpoint: Path | str | None = None,
    progress: bool = True,
    profile: DatasetProfile | None = None,
    precision: str = "fp32",
    leaderboard: LeaderboardEntry | None = None,
    overwrite: bool = False,
    panoptic: bool = False,
) -> Path:
    """Run the demo into `out` (default: a new timestamped folder) and return the folder.

    `leaderboard` gives the first lines of the archive's description.txt (default: the
    benchmark's defaults). An `out` whose predictions tree holds predictions from other weights
    is refused before anything is written unless `overwrite` (every scan is predicted again).

    With a `profile` other than SemanticKITTI's the scans are that dataset's (layout, point
    record, labels), the checkpoint must be a network for it (only SemanticKITTI and nuScenes
    have bundled demo weights), and only nuScenes has a submission archive besides
    SemanticKITTI.

    With `panoptic` the scans' objects are found and scored as well, and the archive is the
    profile's panoptic benchmark's; a profile without thing classes, or without a panoptic
    benchmark to score by, is refused before anything is written.
    """
    import ray

    if profile is not None and checkpoint is None:
        demo_checkpoint(profile.name)  # refuses a profile without bundled weights before any work
    started = time.perf_counter()
    out = Path(out) if out else Path(f"rangeret-demo-{time.strftime('%Y%m%d-%H%M%S')}")
    dataset, preds = out / "dataset", out / "predictions"
    spec = InferenceSpec(
        checkpoint=None if checkpoint is None else str(checkpoint),
        precision=precision,
        panoptic=panoptic,
    )
    loaded = load_weights(spec, profile=profile)
    info, profile = loaded.info, loaded.profile
    benchmark = benchmark_of(profile, panoptic=panoptic)
    if panoptic:
        _check_panoptic(profile, benchmark)
    weights = Path(info.path)
    check_weights(preds, info.sha256, overwrite=overwrite, panoptic=panoptic)
    out.mkdir(parents=True, exist_ok=True)
    plan = benchmark.demo_plan(profile, valid_scans, test_scans)
    demo_weights = is_demo_path(weights)
    n = simulate_tree(
        dataset,
        plan.sequences,
        labelled=list(plan.labelled),
        sensor=plan.sensor,
        seed=2026,
        progress=progress,
        profile=profile,
    )
    log.info("simulated %d scans into %s", n, dataset)
    selection = DatasetSelection(
        dataset, tuple(plan.sequences), profile.layout, plan.split, panoptic=panoptic
    )

    options = PipelineOptions(read_cpus=0.25, write_cpus=0.1)
    write_run_info(
        preds,
        describe_spec(spec, info, profile),
        runner="rangeret demo",
        dataset=dataset,
        sequences=list(selection.sequences),
        batch_size=options.batch_size,
        overwrite=overwrite,
    )
    with contextlib.ExitStack() as stack:
        ray_logs = (
            None if ray.is_initialized() else stack.enter_context(_local_ray(out / RAY_FOLDER))
        )
        entries = selection.discover().scans
        run = run_pipeline(spec, profile, entries, preds, options, checkpoint_sha256=info.sha256)
    if not run.summary.ok:
        raise RuntimeError(f"the demo could not predict {sorted(run.summary.failed)}")

    evaluated = selection.only(plan.labelled)
    report: EvaluationReport | PanopticReport
    if panoptic:
        assert benchmark.panoptic_rules is not None  # _check_panoptic refused it otherwise
        report = evaluate_panoptic(
            evaluated,
            preds,
            profile=profile,
            rules=benchmark.panoptic_rules,
            benchmark=benchmark.name,
            checkpoint_sha256=info.sha256,
        )
        plots: list[Path] = []
    else:
        report = evaluate_predictions(
            evaluated, preds, checkpoint_sha256=info.sha256, profile=profile
        )
        if demo_weights:
            report.notes.append(demo_warning(profile.name))
        plots = write_plots(report, out / "plots", config=profile.labels)
    report.write_json(out / "report.json")
    plots.append(
        _range_image_png(
            selection.only(plan.labelled[:1]), preds, profile, out / "plots" / "range-image.png"
        )
    )

    archive = out / "submission.zip"
    if benchmark.writes_archives:
        leaderboard = leaderboard or LeaderboardEntry()
        request = ArchiveRequest(
            archive,
            dataset,
            profile,
            selection.archive_options(),
            allow_partial=plan.partial_archive,
            progress=progress,
            predictions=preds,
            description=description_text(
                leaderboard,
                written_by="rangeret demo",
                checkpoint_sha256=info.sha256,
                model=info.name,
                profile=profile.name,
                demo_weights=demo_weights,
                notes=["simulated scans: not a real submission"],
            ),
            leaderboard=leaderboard,
            checkpoint_sha256=info.sha256,
        )
        check = benchmark.write_archive(request)
        check.raise_for_problems()

    print(report.table())
    if isinstance(report, PanopticReport):
        head, scans = report.headline(), report.num_scans
        print(
            f"\nPQ {100 * head['pq']:.2f} %, mIoU {100 * head['miou']:.2f} % "
            f"({report.benchmark} rules, {scans} scan{'s' if scans != 1 else ''})"
        )
    print(
        f"\nDone in {time.perf_counter() - started:.0f} s with {info.name} at "
        f"{profile.projection.height}x{profile.projection.width} on {run.actors_text()}. Results in "
        f"{out}/:"
    )
    print(f"  dataset (simulated, {profile.name} layout):".ljust(42) + f" {dataset}")
    print(f"  predictions tree:                         {preds}")
    kind = "panoptic evaluation report:" if panoptic else "evaluation report:"
    print(f"  {kind}".ljust(44) + f"{out / 'report.json'}")
    for p in plots:
        print(f"  plot:                                     {p}")
    if benchmark.writes_archives and plan.partial_archive:
        print(f"  submission archive (partial, for tests):  {archive}")
        print(
            f"    (it holds the demo's few scans: rangeret validate-submission {archive} "
            f"--dataset {dataset} --allow-partial{' --task panoptic' if panoptic else ''} "
            "checks it)"
        )
    elif benchmark.writes_archives:
        print(f"  submission archive ({plan.split}):".ljust(43) + f" {archive}")
    if ray_logs is not None:
        print(f"  Ray's own logs:                           {ray_logs}")
        token = ray_logs.parent / TOKEN_FILE
        if token.is_file():
            print(f"  Ray's token (this run's only):            {token}")
    if demo_weights:
        print(f"\nNote: {demo_warning(profile.name)}.")
    if plan.hints:
        print("\n" + "\n".join(plan.hints))
        if panoptic:
            print(PANOPTIC_HINT)
    return out


def _check_panoptic(profile: DatasetProfile, benchmark: Benchmark) -> None:
    """Refuse a panoptic demo the profile cannot run: no thing classes, or no panoptic
    benchmark to score by."""
    refusal = profile.panoptic_refusal()
    if refusal is not None:
        raise InputError(refusal)
    if benchmark.panoptic_rules is None:
        raise InputError(
            f"the {profile.name} profile has no panoptic benchmark to score by (its "
            "`benchmark.panoptic` names none)"
        )


def _range_image_png(
    selection: DatasetSelection, preds: Path, profile: DatasetProfile, path: Path
) -> Path:
    """The first scan of the selection: its range image, ground truth and prediction as one
    PNG."""
    config = profile.labels
    entry = selection.discover(with_labels=True).scans[0]
    proj = project_with(read_scan(entry.scan_path, profile.points), profile.projection)
    truth = entry.label_file.read(entry.label_path)
    predicted = entry.label_file.read(entry.prediction_in(preds))
    if selection.panoptic:
        semantic = profile.layout.panoptic_encoding.semantic
        truth, predicted = semantic(truth), semantic(predicted)
    gt = config.to_class(truth).astype(np.int64)
    pred = profile.prediction_classes(predicted).astype(np.int64)
    return plot_range_image(
        proj.proj_range,
        proj.to_image(gt),
        proj.to_image(pred),
        path,
        config=config,
        title=f"simulated scan {entry.key}",
    )


#: The demo's Ray's folder in its results: the token and, once it stops, its logs.
RAY_FOLDER = "ray"
#: The file in a Ray session's log folder that takes what Ray writes to the demo's stderr.
RAY_STDERR_LOG = "driver-stderr.log"


@contextlib.contextmanager
def _local_ray(folder: Path) -> Iterator[Path]:
    """A local Ray for the demo, shut down at the end, whose own output stays out of the demo's:
    what Ray writes to this process's stderr (its loggers, its core worker's C++ log lines) goes
    to `RAY_STDERR_LOG` in the session's log folder, beside the logs Ray keeps there, while the
    demo's log lines still reach the terminal. Its token is `folder/auth_token` (not one in the
    home folder), and at the end its logs move to `folder/logs` and its session folder under /tmp
    is removed. Yields where the logs will be."""
    import ray

    kept = folder / "logs"
    with run_token(folder):
        redirect = _StderrRedirect()
        try:
            context = start_local(
                address="local", num_cpus=os.cpu_count() or 2, log_to_driver=False
            )
        except BaseException:
            redirect.stop(show=True)
            shutil.rmtree(session_folder(), ignore_errors=True)
            raise
        logs = Path(context.address_info["session_dir"]) / "logs"
        redirect.move(logs / RAY_STDERR_LOG)
        try:
            yield kept
        except BaseException:
            log.warning("what Ray wrote to stderr in this run is in %s", kept / RAY_STDERR_LOG)
            raise
        finally:
            try:
                ray.shutdown()
            finally:
                redirect.stop(show=False)
                keep_logs(Path(session_folder()), logs, kept)


class _StderrRedirect:
    """File descriptor 2, `sys.stderr` and the other libraries' log handlers that wrote to it
    pointed at a file (first a temporary one, then `move`'s), with the root logger's handlers
    (this program's log lines) still writing to the terminal."""

    def __init__(self) -> None:
        self.saved = sys.stderr
        self.saved.flush()
        self.terminal_fd = os.dup(2)
        self.terminal: IO[str] | None = None
        loggers = [logging.getLogger()] + [
            logger
            for logger in logging.Logger.manager.loggerDict.values()
            if isinstance(logger, logging.Logger)
        ]
        handlers = {
            handler: logger is loggers[0]
            for logger in loggers
            for handler in logger.handlers
            if isinstance(handler, logging.StreamHandler) and handler.stream is self.saved
        }
        self.ours = [h for h, root in handlers.items() if root]
        self.theirs = [h for h, root in handlers.items() if not root]
        if _fileno(self.saved) == 2:
            self.terminal = open(  # noqa: SIM115 (closed by stop)
                self.terminal_fd, "w", buffering=1, closefd=False, errors="backslashreplace"
            )
            for handler in self.ours:
                handler.setStream(self.terminal)
        self.file: IO[str] = tempfile.TemporaryFile("w+", errors="backslashreplace")  # noqa: SIM115
        self._point_at(self.file)

    def _point_at(self, file: IO[str]) -> None:
        sys.stderr.flush()
        os.dup2(file.fileno(), 2)
        sys.stderr = file
        for handler in self.theirs:
            handler.setStream(file)

    def move(self, path: Path) -> None:
        """Go on in `path` (appended to), with what was written so far."""
        self.file.flush()
        self.file.seek(0)
        written = self.file.read()
        target = open(path, "a", buffering=1, errors="backslashreplace")  # noqa: SIM115
        target.write(written)
        self._point_at(target)
        self.file.close()
        self.file = target

    def stop(self, show: bool) -> None:
        """Point everything back at the terminal; with `show`, write there what the file got."""
        self.file.flush()
        os.dup2(self.terminal_fd, 2)
        sys.stderr = self.saved
        for handler in self.ours + self.theirs:
            handler.setStream(self.saved)
        if show:
            self.file.seek(0)
            self.saved.write(self.file.read())
            self.saved.flush()
        self.file.close()
        if self.terminal is not None:
            self.terminal.close()
        os.close(self.terminal_fd)


def _fileno(stream: object) -> int | None:
    """The file descriptor a stream writes to, None when it has none."""
    try:
        return stream.fileno()  # type: ignore[attr-defined]
    except (AttributeError, OSError, ValueError):
        return None
