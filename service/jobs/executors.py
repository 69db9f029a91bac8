"""Running a job's scans through the network, and zipping the predictions it wrote.

`LocalExecutor` runs `predict_tree` in this process; `RayExecutor` sends the scans through the Ray
pipeline of the connected cluster. Both read the scans with the served profile's layout and point
record, and skip the scans whose prediction is already written, so an interrupted job resumes
where it stopped.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from rangeret.atomic import atomic_path
from rangeret.inference import Predictor, PredictorSpec
from rangeret.layout import ScanEntry, prediction_path
from rangeret.predict import is_complete, predict_tree
from rangeret.profiles import DEFAULT_PROFILE, DatasetProfile, load_profile
from rangeret.submission import TEST_SEQUENCES, required_directories
from rangeret.zipfiles import ReproducibleZip

if TYPE_CHECKING:
    from workers.pool import ScanPool

Progress = Callable[[int, int, int], None]


class JobExecutor(Protocol):
    """Runs the network over a job's scans (in this process or on a Ray cluster)."""

    backend: str
    #: The precision the network ran at in the last `predict` (None before the first).
    precision: str | None
    #: The inference backend that runs the network (torch or onnxruntime).
    inference_backend: str

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: threading.Event,
    ) -> dict[str, str]:
        """Write the predictions of the scans not done yet; return failures by scan key."""
        ...


class LocalExecutor:
    """`predict_tree` in this process, with its own predictor (built on first use), which reads
    the dataset in the layout and point record of the profile the spec's network runs with."""

    backend = "local"

    def __init__(self, spec: PredictorSpec, batch_size: int = 1) -> None:
        self.spec = spec
        self.batch_size = batch_size
        self.precision: str | None = None
        self._predictor: Predictor | None = None

    @property
    def inference_backend(self) -> str:
        """The backend the spec runs the network with."""
        return self.spec.backend

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: threading.Event,
    ) -> dict[str, str]:
        """Predict the dataset's sequences into `out`, skipping scans already done."""
        if self._predictor is None:
            self._predictor = self.spec.build()
        self.precision = self._predictor.precision
        summary = predict_tree(
            self._predictor,
            dataset,
            sequences,
            out,
            batch_size=self.batch_size,
            progress=False,
            on_progress=progress,
            cancel=cancel,
        )
        return summary.failed


class RayExecutor:
    """`workers.pipeline.run_pipeline` on the connected Ray cluster.

    Given the gateway's `pool` of GPU actors, jobs run on those actors (single-scan requests wait
    behind at most two of a job's batches), since the pool holds one actor per GPU and a job would
    find none free. Otherwise each job starts its own model actors (`actors`, or the pipeline's
    default: one per free GPU, or per free CPU of a CPU cluster).
    """

    backend = "ray"

    def __init__(
        self,
        spec: PredictorSpec,
        profile: DatasetProfile,
        batch_size: int = 1,
        actors: int | None = None,
        pool: ScanPool | None = None,
    ) -> None:
        self.spec = spec
        self.profile = profile
        self.batch_size = batch_size
        self.actors = actors
        self.pool = pool
        self.precision: str | None = None

    @property
    def inference_backend(self) -> str:
        """The backend the spec runs the network with."""
        return self.spec.backend

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: threading.Event,
    ) -> dict[str, str]:
        """Send the scans without a finished prediction through the pipeline."""
        from workers.pipeline import PipelineOptions, run_pipeline

        pending = [e for e in entries if not is_complete(e, out, self.profile.points)]
        options = PipelineOptions(batch_size=self.batch_size, actors=self.actors)
        shared = self.pool.actors if self.pool is not None and self.pool.use_gpu else None
        result = run_pipeline(
            self.spec,
            self.profile,
            pending,
            out,
            options,
            progress=progress,
            cancel=cancel,
            model_actors=shared,
        )
        self.precision = result.precision(self.spec) or self.precision
        return result.failed


def write_predictions_zip(
    pred_root: Path,
    entries: Sequence[ScanEntry],
    sequences: Sequence[str],
    path: Path,
    description: str,
    profile: DatasetProfile | None = None,
    workers: int | None = None,
) -> None:
    """The job's predictions as a reproducible zip with explicit directory entries, as
    `sequences/<id as on disk>/predictions/NNNNNN.label` for every profile (default semantickitti).

    When the profile is SemanticKITTI's and all the sequences are its test sequences, the archive
    holds the directory entries of every test sequence, as the benchmark server wants, so it
    passes the submission validator. The labels are read and deflated in `workers` threads
    (default: every CPU this process may use); the archive's bytes do not depend on it.
    """
    names = list(dict.fromkeys(sequences))
    benchmark = (profile or load_profile(None)).name == DEFAULT_PROFILE
    if benchmark and all(s in TEST_SEQUENCES for s in names):
        directories = list(required_directories())
    else:
        directories = ["sequences/"]
        for seq in sorted(names):
            directories += [f"sequences/{seq}/", f"sequences/{seq}/predictions/"]
    with atomic_path(path) as tmp, ReproducibleZip(tmp) as zf:
        for name in directories:
            zf.add_directory(name)
        zf.add_files(
            (
                (
                    f"sequences/{entry.sequence}/predictions/{entry.name}.label",
                    prediction_path(pred_root, entry.sequence, entry.name).read_bytes,
                )
                for entry in entries
            ),
            workers,
        )
        zf.add_file("description.txt", description.rstrip("\n") + "\n")
