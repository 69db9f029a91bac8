"""From points to raw SemanticKITTI labels: projection, the network, kNN refinement, raw ids.

`Predictor` holds a loaded network and the options of a run. Its stages are separate methods
(`project`, `logits`, `refine_batch`, `to_raw`) so a pipeline can run them on different workers;
`predict` and `predict_batch` chain them for one process. Each stage records its time in the
`StageTimes` its caller passes (a run's own record), or else in the predictor's `times`.
Refinement runs per batch (`refine_batch`), one scan being a batch of one.
Output is deterministic: the same weights, options and batch size give the same labels
everywhere.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.projection import Projection, ProjectionConfig, project_with
from rangeret.inference.description import describe_network
from rangeret.inference.loading import LoadedScan
from rangeret.inference.point_labels import point_classes_batch, point_confidences
from rangeret.inference.results import ScanOutcome, ScanPrediction
from rangeret.inference.runtime.device import select_device
from rangeret.inference.runtime.onnx_backend import OnnxForward, cached_export
from rangeret.inference.runtime.precision import forward_precision, resolve_precision
from rangeret.inference.settings import DEFAULT_KNN, KnnSettings, TtaSettings
from rangeret.inference.timing import StageTimes
from rangeret.inference.tta import transformed_view
from rangeret.models.weights.checkpoint import CheckpointError, load_checkpoint
from rangeret.models.weights.checkpoint_info import CheckpointInfo
from rangeret.models.weights.hub import resolve_weights
from rangeret.models.weights.run_profile import default_resolution, profile_for_checkpoint

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PredictorSpec:
    """Everything needed to build the same `Predictor` in another process (a Ray worker)."""

    checkpoint: str
    model: str | None = None
    profile: DatasetProfile | None = None
    height: int | None = None
    width: int | None = None
    fov_up: float | None = None
    fov_down: float | None = None
    device: str = "auto"
    precision: str = "auto"
    knn: KnnSettings | None = DEFAULT_KNN
    tta: TtaSettings | None = None
    backend: str = "torch"

    def build(self) -> Predictor:
        """Load the checkpoint and make the predictor."""
        return Predictor.from_checkpoint(
            self.checkpoint,
            model=self.model,
            profile=self.profile,
            height=self.height,
            width=self.width,
            fov_up=self.fov_up,
            fov_down=self.fov_down,
            device=self.device,
            precision=self.precision,
            knn=self.knn,
            tta=self.tta,
            backend=self.backend,
        )


class Predictor:
    """A loaded network plus the dataset profile (projection, refinement rule, label map) it runs
    with. With `backend="onnxruntime"` the network's forward pass runs in an onnxruntime session
    of its export (`rangeret.inference.runtime.onnx_backend`); the network itself then stays on the CPU."""

    def __init__(
        self,
        network: torch.nn.Module,
        profile: DatasetProfile,
        device: str | torch.device = "auto",
        knn: KnnSettings | None = DEFAULT_KNN,
        tta: TtaSettings | None = None,
        checkpoint_sha256: str | None = None,
        precision: str = "auto",
        backend: str = "torch",
    ) -> None:
        classes = _network_classes(network)
        if classes is not None and classes != profile.num_classes:
            raise CheckpointError(
                f"the network predicts {classes} classes but the {profile.name} profile has "
                f"{profile.num_classes}: it was not made for this dataset"
            )
        self.device = select_device(device)
        self.precision = resolve_precision(precision, self.device, backend)
        self.backend = backend
        self.profile = profile
        self.knn = knn
        self.tta = tta
        self.checkpoint_sha256 = checkpoint_sha256
        self.onnx: OnnxForward | None = None
        if backend == "onnxruntime":
            self.network = network.cpu().eval()
            self.onnx = OnnxForward(self.network, profile, self.device, checkpoint_sha256)
        else:
            self.network = network.to(self.device).eval()
        self.times = StageTimes()  # where stages record unless the caller passes its own record

    @property
    def projection_config(self) -> ProjectionConfig:
        """The projection of the profile, at the network's resolution."""
        return self.profile.projection

    @property
    def label_config(self) -> LabelConfig:
        """The profile's label configuration."""
        return self.profile.labels

    @property
    def num_classes(self) -> int:
        """Classes the network predicts (the profile's)."""
        return self.profile.num_classes

    @classmethod
    def from_checkpoint(
        cls,
        path: str | Path,
        model: str | None = None,
        profile: DatasetProfile | None = None,
        height: int | None = None,
        width: int | None = None,
        fov_up: float | None = None,
        fov_down: float | None = None,
        device: str | torch.device = "auto",
        knn: KnnSettings | None = DEFAULT_KNN,
        tta: TtaSettings | None = None,
        precision: str = "auto",
        backend: str = "torch",
    ) -> Predictor:
        """A predictor for a checkpoint file, the project's own (self-describing) or a published
        one, or for a published model's registered name (its file fetched, its profile taken).

        The project's own files run with the profile they record (asking for another one is an
        error). Published files record none: they run with `profile` (else SemanticKITTI's),
        which gives their resolution and field of view unless height, width or fov are given.
        """
        weights = resolve_weights(path, profile, model, height, width)
        profile = weights.profile
        network = load_checkpoint(
            weights.path,
            model=weights.model,
            height=weights.height,
            width=weights.width,
            default_resolution=default_resolution(profile),
        )
        info = network.checkpoint_info
        resolved = profile_for_checkpoint(info, requested=profile, fov_up=fov_up, fov_down=fov_down)
        return cls(
            network,
            resolved,
            device,
            knn,
            tta,
            checkpoint_sha256=info.sha256,
            precision=precision,
            backend=backend,
        )

    def describe(self) -> dict:
        """Plain-data description of the run's settings, for logs, reports and `run.json`."""
        info = getattr(self.network, "checkpoint_info", None)
        return describe_network(
            model=getattr(info, "name", type(self.network).__name__),
            checkpoint=getattr(info, "path", None),
            sha256=self.checkpoint_sha256,
            profile=self.profile.name,
            projection=self.projection_config,
            knn=self.knn,
            tta=self.tta,
            device=str(self.device),
            precision=self.precision,
            backend=self.backend,
        )

    def with_knn(self, knn: KnnSettings | None) -> Predictor:
        """The same predictor with another kNN refinement (None: pixel classes), sharing the
        network, its onnxruntime session and every other setting."""
        other = copy.copy(self)
        other.knn = knn
        other.times = StageTimes()
        return other

    # Stages -------------------------------------------------------------------------------

    def project(self, points: np.ndarray, times: StageTimes | None = None) -> Projection:
        """Stage 1 (CPU): the scan's range image and every point's pixel."""
        with self._record(times).stage("project"):
            return project_with(points, self.projection_config)

    @torch.inference_mode()
    def logits(
        self, projections: Sequence[Projection], times: StageTimes | None = None
    ) -> torch.Tensor:
        """Stage 2: float32 logits (B, C, H, W) for a batch of projected scans, on the device."""
        with self._record(times).stage("network", len(projections)):
            batch = torch.from_numpy(np.stack([p.image for p in projections])).to(self.device)
            logits = self._forward(batch) if self.tta is None else self._forward_tta(batch)
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            return logits

    def refine_batch(
        self,
        projections: Sequence[Projection],
        logits: torch.Tensor,
        times: StageTimes | None = None,
    ) -> list[np.ndarray]:
        """Stage 3 for a batch: each scan's per-point classes from (B, C, H, W) logits, refined in
        one call so the device does not wait on the host scan by scan."""
        with self._record(times).stage("refine", len(projections)):
            classes = point_classes_batch(
                logits.argmax(dim=1),
                [p.proj_x for p in projections],
                [p.proj_y for p in projections],
                [p.proj_range for p in projections],
                [p.unproj_range for p in projections],
                self.knn,
                self.num_classes,
                votes_from=self.profile.knn.votes_from,
                unlabeled=self.label_config.unlabeled_class,
            )
            ends = np.cumsum([p.num_points for p in projections])
            return np.split(classes.cpu().numpy(), ends[:-1])

    def to_raw(self, classes: np.ndarray) -> np.ndarray:
        """Stage 4: raw SemanticKITTI ids (uint32) of training classes."""
        return self.label_config.to_raw(classes)

    # Whole scans ---------------------------------------------------------------------------

    def predict(self, points: np.ndarray) -> ScanPrediction:
        """Raw labels, one per point, for one (N, 4) scan."""
        return self.predict_batch([points])[0]

    def predict_batch(self, scans: Sequence[np.ndarray]) -> list[ScanPrediction]:
        """Raw labels for several scans, run through the network as one batch."""
        return self.finish_batch([self.project(p) for p in scans])

    def finish_batch(
        self,
        projections: Sequence[Projection],
        times: StageTimes | None = None,
        with_confidence: bool = False,
    ) -> list[ScanPrediction]:
        """Stages 2 to 4 for a batch of projected scans: every runner's path from projection to
        raw labels (one process, the Ray model actors, the gateway's actors); with
        `with_confidence`, each point's confidence in its label too."""
        logits = self.logits(projections, times)
        classes = self.refine_batch(projections, logits, times)
        confidences: list[np.ndarray | None] = [None] * len(projections)
        if with_confidence:
            confidences = point_confidences(
                logits, [p.proj_x for p in projections], [p.proj_y for p in projections], classes
            )
        return [
            ScanPrediction(labels=self.to_raw(c), classes=c, confidence=conf)
            for c, conf in zip(classes, confidences, strict=True)
        ]

    def label_projected(
        self,
        scans: Sequence[Projection | str],
        times: StageTimes | None = None,
        with_confidence: bool = False,
    ) -> list[ScanOutcome]:
        """A prediction for each projected scan of a batch and, for a scan given as the reason it
        has no projection, that reason, in order. The network runs once on the projected scans;
        its errors propagate (see `label_loaded`)."""
        good = [s for s in scans if not isinstance(s, str)]
        done = iter(
            self.finish_batch(good, times=times, with_confidence=with_confidence) if good else []
        )
        return [s if isinstance(s, str) else next(done) for s in scans]

    def label_loaded(
        self,
        scans: Sequence[LoadedScan],
        times: StageTimes | None = None,
        with_confidence: bool = False,
    ) -> list[ScanOutcome]:
        """A prediction or the named failure of each scan of a loaded batch, in order.

        The network runs once on the readable scans; if it fails (out of device memory, say),
        each of them becomes a named failure instead of stopping the run.
        """
        try:
            return self.label_projected(
                [s.error if s.error is not None else s.projection for s in scans],
                times,
                with_confidence,
            )
        except RuntimeError as exc:
            reason = f"the network failed: {exc}"
            return [s.error or reason for s in scans]

    # Internals -----------------------------------------------------------------------------

    def _record(self, times: StageTimes | None) -> StageTimes:
        return self.times if times is None else times

    def _forward(self, batch: torch.Tensor) -> torch.Tensor:
        if self.onnx is not None:
            return self.onnx(batch)
        with forward_precision(self.precision, self.device):
            return self.network(batch).float()

    def _forward_tta(self, batch: torch.Tensor) -> torch.Tensor:
        """Mean logits over mirrored and azimuth-rotated views, each mapped back to the original."""
        width = batch.shape[-1]
        total = None
        views = self.tta.views(width)
        for flipped, shift in views:
            view = transformed_view(batch, flipped, shift, self.projection_config)
            logits = self._forward(view)
            if shift:
                logits = torch.roll(logits, -shift, dims=-1)
            if flipped:
                logits = torch.flip(logits, dims=[-1])
            total = logits if total is None else total + logits
        return total / len(views)


def _network_classes(network: torch.nn.Module) -> int | None:
    config = getattr(network, "config", None)
    return getattr(config, "num_classes", None)


def checkpoint_profile(spec: PredictorSpec) -> tuple[CheckpointInfo, DatasetProfile]:
    """Load `spec`'s checkpoint once (on the CPU) to check it and resolve the profile it runs
    with, for drivers that build predictors elsewhere (the Ray job, the gateway). With the
    onnxruntime backend the export is made here too, once, so that the workers started next load
    it from the cache instead of each exporting it."""
    network = load_checkpoint(
        spec.checkpoint,
        model=spec.model,
        height=spec.height,
        width=spec.width,
        default_resolution=default_resolution(spec.profile),
    )
    info = network.checkpoint_info
    profile = profile_for_checkpoint(
        info, requested=spec.profile, fov_up=spec.fov_up, fov_down=spec.fov_down
    )
    if spec.backend == "onnxruntime":
        cached_export(network, profile, info.sha256)
    return info, profile
