"""From points to raw SemanticKITTI labels: projection, the network, kNN refinement, raw ids.

`Predictor` holds a loaded network and the options of a run. Its stages are separate methods
(`project`, `logits`, `refine`, `to_raw`) so a pipeline can run them on different workers;
`predict` and `predict_batch` chain them for one process. Each stage records its time in the
`StageTimes` its caller passes (a run's own record), or else in the predictor's `times`.
Output is deterministic: the same weights, options and batch size give the same labels
everywhere.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from rangeret.hub import resolve_weights
from rangeret.labels import LabelConfig
from rangeret.loading import LoadedScan
from rangeret.models import CheckpointError, CheckpointInfo, load_checkpoint
from rangeret.onnx_backend import OnnxForward, cached_export
from rangeret.point_labels import (
    DEFAULT_KNN,
    KnnSettings,
    point_classes_batch,
    point_confidences,
)
from rangeret.precision import forward_precision, resolve_precision
from rangeret.profiles import DatasetProfile, load_profile, profile_of_record
from rangeret.projection import Projection, ProjectionConfig, project_with
from rangeret.timing import StageTimes

log = logging.getLogger(__name__)

#: The bundled demo weights: trained on simulated scenes only (see data/DEMO_WEIGHTS.md).
DEMO_CHECKPOINT = Path(__file__).with_name("data") / "demo-weights.pt"
DEMO_WARNING = (
    "using the bundled demo weights, trained on simulated street scenes only: their labels on "
    "real scans are not meaningful; pass --checkpoint with real weights such as "
    "rangeret-kitti-657 (`rangeret weights list`)"
)


def resolve_checkpoint(path: str | Path | None) -> Path:
    """The checkpoint to load: `path`, a published model's file when `path` is its registered
    name (`rangeret-kitti-657`, fetched from the cache or the hub), or the bundled demo weights
    (announced loudly) when None."""
    if path is not None:
        return resolve_weights(path).path
    if not DEMO_CHECKPOINT.exists():
        raise FileNotFoundError(
            f"no --checkpoint given and the bundled demo weights {DEMO_CHECKPOINT} are missing"
        )
    log.warning(DEMO_WARNING)
    return DEMO_CHECKPOINT


def is_demo_checkpoint(sha256: str | None) -> bool:
    """Whether a checkpoint hash is that of the bundled demo weights."""
    return bool(sha256) and sha256 == _demo_sha256()


@functools.cache
def _demo_sha256() -> str | None:
    """The bundled demo weights' SHA-256, read once (every description of a run asks for it)."""
    if not DEMO_CHECKPOINT.exists():
        return None
    return hashlib.sha256(DEMO_CHECKPOINT.read_bytes()).hexdigest()


@dataclass(frozen=True)
class TtaSettings:
    """Test-time augmentation: mirror the range image and/or rotate it in azimuth, average logits."""

    flip: bool = True
    shifts: int = 0

    def views(self, width: int) -> list[tuple[bool, int]]:
        """(flipped, column shift) of every view, the identity first."""
        shifts = [round(i * width / (self.shifts + 1)) for i in range(self.shifts + 1)]
        return [(f, s) for f in ([False, True] if self.flip else [False]) for s in shifts]


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


def describe_network(
    *,
    model: str,
    checkpoint: str | None,
    sha256: str | None,
    profile: str,
    projection: ProjectionConfig,
    knn: KnnSettings | None,
    tta: TtaSettings | None,
    device: str,
    precision: str,
    backend: str = "torch",
) -> dict:
    """The description of a network and its options that logs, reports and `run.json` carry;
    `device` and `precision` are those used, or those asked for where the network runs
    elsewhere; `backend` is where its forward pass runs (torch or onnxruntime)."""
    return {
        "model": model,
        "checkpoint": checkpoint,
        "checkpoint_sha256": sha256,
        "demo_weights": is_demo_checkpoint(sha256),
        "profile": profile,
        "projection": projection.to_dict(),
        "knn": asdict(knn) if knn else None,
        "tta": asdict(tta) if tta else None,
        "device": device,
        "precision": precision,
        "backend": backend,
    }


def select_device(device: str | torch.device = "auto") -> torch.device:
    """`auto` picks CUDA when torch sees a GPU and the CPU otherwise; `cuda` without one is an error."""
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for but torch sees no CUDA device")
    return dev


@dataclass
class ScanPrediction:
    """The result for one scan: raw labels (one per point) and what led to them."""

    labels: np.ndarray
    classes: np.ndarray
    probabilities: np.ndarray | None = None
    #: Each point's softmax probability of its final class at its pixel (float32), when asked.
    confidence: np.ndarray | None = None


class Predictor:
    """A loaded network plus the dataset profile (projection, refinement rule, label map) it runs
    with. With `backend="onnxruntime"` the network's forward pass runs in an onnxruntime session
    of its export (`rangeret.onnx_backend`); the network itself then stays on the CPU."""

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
        error). Published files record none: they run with `profile` (default `semantickitti`),
        which gives their resolution and field of view unless height, width or fov are given.
        """
        weights = resolve_weights(path, profile, model, height, width)
        profile = weights.profile
        network = load_checkpoint(
            weights.path,
            model=weights.model,
            height=weights.height,
            width=weights.width,
            default_resolution=_resolution(profile),
        )
        info = network.checkpoint_info
        resolved = profile_for_checkpoint(info, profile, fov_up, fov_down)
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

    def refine(
        self, projection: Projection, logits: torch.Tensor, times: StageTimes | None = None
    ) -> np.ndarray:
        """Stage 3: per-point training classes from one scan's (C, H, W) logits."""
        return self.refine_batch([projection], logits[None], times)[0]

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

    def probabilities(self, projection: Projection, logits: torch.Tensor) -> np.ndarray:
        """(N, C) float32 softmax of each point's pixel; zeros for points without a pixel."""
        probs = torch.softmax(logits.float(), dim=0).cpu().numpy()
        out = np.zeros((projection.num_points, probs.shape[0]), dtype=np.float32)
        valid = projection.proj_x >= 0
        out[valid] = probs[:, projection.proj_y[valid], projection.proj_x[valid]].T
        return out

    # Whole scans ---------------------------------------------------------------------------

    def predict(self, points: np.ndarray, with_probabilities: bool = False) -> ScanPrediction:
        """Raw labels, one per point, for one (N, 4) scan."""
        return self.predict_batch([points], with_probabilities)[0]

    def predict_batch(
        self, scans: Sequence[np.ndarray], with_probabilities: bool = False
    ) -> list[ScanPrediction]:
        """Raw labels for several scans, run through the network as one batch."""
        projections = [self.project(p) for p in scans]
        return self.finish_batch(projections, with_probabilities)

    def finish_batch(
        self,
        projections: Sequence[Projection],
        with_probabilities: bool = False,
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
            ScanPrediction(
                labels=self.to_raw(c),
                classes=c,
                probabilities=self.probabilities(p, out) if with_probabilities else None,
                confidence=conf,
            )
            for p, out, c, conf in zip(projections, logits, classes, confidences, strict=True)
        ]

    def label_loaded(
        self,
        scans: Sequence[LoadedScan],
        times: StageTimes | None = None,
        with_confidence: bool = False,
    ) -> list[tuple[ScanPrediction | None, str | None]]:
        """(prediction, None) or (None, why) for each scan of a loaded batch, in order.

        The network runs once on the readable scans; if it fails (out of device memory, say),
        each of them becomes a named failure instead of stopping the run.
        """
        good = [s.projection for s in scans if s.error is None]
        try:
            done = iter(
                self.finish_batch(good, times=times, with_confidence=with_confidence)
                if good
                else []
            )
        except RuntimeError as exc:
            reason = f"the network failed: {exc}"
            return [(None, s.error or reason) for s in scans]
        return [(None, s.error) if s.error is not None else (next(done), None) for s in scans]

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
            view = _transform(batch, flipped, shift, self.projection_config)
            logits = self._forward(view)
            if shift:
                logits = torch.roll(logits, -shift, dims=-1)
            if flipped:
                logits = torch.flip(logits, dims=[-1])
            total = logits if total is None else total + logits
        return total / len(views)


def _transform(
    batch: torch.Tensor, flipped: bool, shift: int, config: ProjectionConfig
) -> torch.Tensor:
    """A view of normalised range images as if the scene were mirrored (y -> -y) and/or rotated.

    Mirroring flips the columns; rotating by `shift` columns rolls them. The x and y channels are
    transformed with the scene, so the view looks like a real scan to the network.
    """
    if not flipped and not shift:
        return batch
    out = batch.clone()
    mask = (batch != 0).any(dim=1, keepdim=True)
    means = torch.tensor(config.means, dtype=batch.dtype, device=batch.device)
    stds = torch.tensor(config.stds, dtype=batch.dtype, device=batch.device)
    x = batch[:, 1] * stds[1] + means[1]
    y = batch[:, 2] * stds[2] + means[2]
    if flipped:
        y = -y
        out = torch.flip(out, dims=[-1])
        x, y, mask = torch.flip(x, dims=[-1]), torch.flip(y, dims=[-1]), torch.flip(mask, dims=[-1])
    if shift:
        # Column u holds yaw = -atan2(y, x); moving content right by `shift` columns is a rotation
        # of the points by -2 pi shift / W about z.
        angle = -2 * np.pi * shift / batch.shape[-1]
        cos, sin = float(np.cos(angle)), float(np.sin(angle))
        x, y = cos * x - sin * y, sin * x + cos * y
        out = torch.roll(out, shift, dims=-1)
        x, y, mask = (torch.roll(t, shift, dims=-1) for t in (x, y, mask))
    out[:, 1] = torch.where(mask[:, 0], (x - means[1]) / stds[1], 0)
    out[:, 2] = torch.where(mask[:, 0], (y - means[2]) / stds[2], 0)
    return out


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
        default_resolution=_resolution(spec.profile),
    )
    info = network.checkpoint_info
    profile = profile_for_checkpoint(info, spec.profile, spec.fov_up, spec.fov_down)
    if spec.backend == "onnxruntime":
        cached_export(network, profile, info.sha256)
    return info, profile


def profile_for_checkpoint(
    info: CheckpointInfo,
    requested: DatasetProfile | None = None,
    fov_up: float | None = None,
    fov_down: float | None = None,
) -> DatasetProfile:
    """The profile a loaded network runs with, its projection at the network's resolution.

    The project's own files give their recorded profile (files from before profiles: the
    `semantickitti` profile with the stored projection and labels); a `requested` profile of
    another name is a CheckpointError naming both. Published files take `requested` or the
    default. A class count that differs from the profile's is a CheckpointError naming both.
    """
    if info.published:
        profile = requested or load_profile(None)
        projection = profile.projection
    else:
        profile = _recorded_profile(info)
        if requested is not None and requested.name != profile.name:
            raise CheckpointError(
                f"{info.path} was trained for the {profile.name} profile and cannot run with the "
                f"{requested.name} profile; leave --profile out or pass --profile {profile.name}"
            )
        projection = _stored_projection(info.projection) or profile.projection
    projection = replace(projection, height=info.config["height"], width=info.config["width"])
    profile = replace(profile, projection=projection).with_overrides(
        fov_up=fov_up, fov_down=fov_down
    )
    classes = int(info.config["num_classes"])
    if classes != profile.num_classes:
        raise CheckpointError(
            f"{info.path} predicts {classes} classes but the {profile.name} profile has "
            f"{profile.num_classes}: the network was not made for this dataset "
            "(choose its profile with --profile)"
        )
    return profile


def _recorded_profile(info: CheckpointInfo) -> DatasetProfile:
    """The profile a project checkpoint records; SemanticKITTI's for files from before profiles,
    with the label configuration they stored."""
    if info.profile:
        return profile_of_record(info.profile, info.path)
    profile = load_profile(None)
    if info.label_config:
        profile = replace(profile, labels=LabelConfig.from_dict(info.label_config))
    return profile


def _stored_projection(record: dict | None) -> ProjectionConfig | None:
    """The projection stored in a project checkpoint, if any."""
    if not record:
        return None
    stored = dict(record)
    for key in ("means", "stds"):
        if key in stored:
            stored[key] = tuple(stored[key])
    return ProjectionConfig(**stored)


def _resolution(profile: DatasetProfile | None) -> tuple[int, int]:
    base = (profile or load_profile(None)).projection
    return base.height, base.width


def _network_classes(network: torch.nn.Module) -> int | None:
    config = getattr(network, "config", None)
    return getattr(config, "num_classes", None)
