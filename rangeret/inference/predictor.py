"""From points to raw labels of the profile's label configuration: projection, the network, kNN
refinement, raw ids.

`Predictor` holds a loaded network and the settings of a run. Its stages are separate methods
(`project`, `logits`, `refine_batch`, `to_raw`) so a pipeline can run them on different workers;
`label_projections` is the one batch entry point every runner calls (a prediction or the named
failure of each scan, one network pass at a time per network), and `predict` labels one scan with
it. Each stage records its time in the `StageTimes` its caller passes, if any. Output is
deterministic: the same weights, options and batch size give the same labels everywhere.
"""

from __future__ import annotations

import copy
import logging
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from rangeret.dataset.label_map import LabelMap
from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.projection import Projection, ProjectionConfig, project_with
from rangeret.exceptions import InputError
from rangeret.inference.description import describe_network
from rangeret.inference.loaded_weights import LoadedWeights, load_weights
from rangeret.inference.point_labels import pixel_classes, point_classes_batch, point_confidences
from rangeret.inference.results import ScanOutcome, ScanPrediction
from rangeret.inference.runtime.device import select_device
from rangeret.inference.runtime.fast_graph import FastGraph, inference_graph
from rangeret.inference.runtime.onnx_backend import OnnxForward
from rangeret.inference.runtime.precision import forward_precision, resolve_precision
from rangeret.inference.settings import DEFAULT_KNN, ClusterSettings, KnnSettings, TtaSettings
from rangeret.inference.spec import InferenceSpec
from rangeret.inference.timing import StageTimes
from rangeret.inference.tta import transformed_view
from rangeret.io.panoptic_labels import PanopticEncodingError

log = logging.getLogger(__name__)


class Predictor:
    """A loaded network plus the dataset profile (projection, refinement rule, label map) and the
    run settings of a spec (device, precision, backend, kNN, test-time augmentation). With
    `backend="onnxruntime"` the forward pass runs in an onnxruntime session of its export
    (`rangeret.inference.runtime.onnx_backend`); the network itself then stays on the CPU."""

    def __init__(self, weights: LoadedWeights, spec: InferenceSpec | None = None) -> None:
        spec = spec or InferenceSpec()
        self.weights = weights
        self.profile = weights.profile
        self.device = select_device(spec.device)
        self.precision = resolve_precision(spec.precision, self.device, spec.backend)
        self.backend = spec.backend
        self.knn: KnnSettings | None = spec.knn_settings
        self.tta: TtaSettings | None = spec.tta
        self.clustering: ClusterSettings | None = None
        self._check_clustering(spec.clustering)
        self.clustering = spec.clustering
        self.onnx: OnnxForward | None = None
        if spec.backend == "onnxruntime":
            self.network = weights.network.cpu().eval()
            self.onnx = OnnxForward(
                self.network,
                self.profile,
                self.device,
                self.checkpoint_sha256,
                export=None if spec.onnx is None else Path(spec.onnx),
                batch_size=spec.batch_size,
            )
        else:
            self.network = weights.network.to(self.device).eval()
        #: The network's inference graph for this run (None: the network runs as it is).
        self.graph: FastGraph | None = (
            None if self.onnx else inference_graph(self.network, self.precision, self.device)
        )
        #: Raw ids of the network's profile -> the data's, for a run on another sensor's data.
        self.output_map: LabelMap | None = None
        self._lock = threading.Lock()  # one network pass at a time, copies (`with_knn`) included

    @classmethod
    def from_spec(cls, spec: InferenceSpec) -> Predictor:
        """The predictor of a spec: its weights loaded once (`load_weights`), its settings kept."""
        return cls(load_weights(spec), spec)

    @classmethod
    def from_network(
        cls, network: torch.nn.Module, profile: DatasetProfile, spec: InferenceSpec | None = None
    ) -> Predictor:
        """A predictor for a network built or loaded by other means, checked against the
        profile's class count."""
        return cls(LoadedWeights.of_network(network, profile), spec)

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
        device: str = "auto",
        knn: KnnSettings | None = DEFAULT_KNN,
        tta: TtaSettings | None = None,
        precision: str = "fp32",
        backend: str = "torch",
    ) -> Predictor:
        """A predictor for a checkpoint file, the project's own (self-describing) or a published
        one, or for a published model's registered name (its file fetched, its profile taken).

        The project's own files run with the profile they record (asking for another one is an
        error). Published files record none: they run with `profile` (else SemanticKITTI's),
        which gives their resolution and field of view unless height, width or fov are given.
        """
        weights = dict(model=model, height=height, width=width, fov_up=fov_up, fov_down=fov_down)
        run = dict(device=device, precision=precision, backend=backend, knn=knn is not None)
        augmented = dict(tta_flip=tta is not None and tta.flip, tta_shifts=tta.shifts if tta else 0)
        spec = InferenceSpec(checkpoint=str(path), **weights, **run, **augmented)
        predictor = cls(load_weights(spec, profile=profile), spec)
        return predictor if knn in (None, DEFAULT_KNN) else predictor.with_knn(knn)

    @property
    def checkpoint_sha256(self) -> str | None:
        """The SHA-256 of the checkpoint file the network came from (None: from no file)."""
        return self.weights.sha256

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

    def describe(self) -> dict:
        """Plain-data description of the run's settings, for logs, reports and `run.json`."""
        info = self.weights.info
        return (
            describe_network(
                model=self.weights.model,
                checkpoint=None if info is None else info.path,
                sha256=self.checkpoint_sha256,
                profile=self.profile.name,
                projection=self.projection_config,
                knn=self.knn,
                tta=self.tta,
                clustering=self.clustering,
                device=str(self.device),
                precision=self.precision,
                backend=self.backend,
                parent=None if info is None else info.parent,
            )
            | self._data_description()
        )

    def _data_description(self) -> dict:
        """For a run on another sensor's data: the network's profile and the label map."""
        if self.output_map is None:
            return {}
        return {
            "network_profile": self.weights.profile.name,
            "label_map": self.output_map.to_dict(),
        }

    def with_knn(self, knn: KnnSettings | None) -> Predictor:
        """The same predictor with another kNN refinement (None: pixel classes), sharing the
        network, its onnxruntime session, its lock and every other setting."""
        other = copy.copy(self)
        other.knn = knn
        return other

    def with_clustering(self, clustering: ClusterSettings | None) -> Predictor:
        """The same predictor that finds objects as `clustering` says (None: classes only),
        sharing everything else; an `InputError` when the profile names no thing class."""
        self._check_clustering(clustering)
        other = copy.copy(self)
        other.clustering = clustering
        return other

    def _check_clustering(self, clustering: ClusterSettings | None) -> None:
        """Refuse panoptic segmentation on a profile without thing classes."""
        refusal = None if clustering is None else self.profile.panoptic_refusal()
        if refusal is not None:
            raise InputError(refusal)

    def for_data(self, data: DatasetProfile, label_map: LabelMap) -> Predictor:
        """The same network on a dataset of another sensor (`data`'s profile): scans read and
        projected as `data` says, the network's classes refined by its own rules and written as
        `data`'s raw ids through `label_map`, which must list every raw id the network writes
        (`rangeret.dataset.other_sensor`)."""
        from rangeret.dataset.other_sensor import output_map, profile_for_data

        if self.onnx is not None:
            raise InputError("a run on another sensor's data takes --backend torch")
        other = copy.copy(self)
        other.profile = profile_for_data(self.weights.profile, data)
        other.output_map = output_map(self.weights.profile, label_map)
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
                pixel_classes(logits, self.profile.benchmark.classes_from),
                [p.proj_x for p in projections],
                [p.proj_y for p in projections],
                [p.proj_range for p in projections],
                [p.unproj_range for p in projections],
                self.knn,
                self.num_classes,
                votes_from=self.profile.knn.votes_from,
                unlabeled=self.profile.unprojected_class,
            )
            ends = np.cumsum([p.num_points for p in projections])
            return np.split(classes.cpu().numpy(), ends[:-1])

    def to_raw(self, classes: np.ndarray) -> np.ndarray:
        """Stage 4: what prediction files hold for training classes (uint32): the profile's raw
        ids, or the classes themselves where its benchmark takes those (nuScenes); on another
        sensor's data, the data's raw ids through the label map."""
        raw = self.profile.output_labels(classes)
        return raw if self.output_map is None else self.output_map.apply(raw)

    def instances(self, projection: Projection, classes: np.ndarray) -> np.ndarray:
        """Stage 5 with panoptic segmentation: each point's object (uint32, unique in the scan,
        0 for stuff), the points of each thing class clustered on the range image."""
        from rangeret.inference.instances import row_gaps, scan_instances

        if self.clustering is None:
            raise ValueError("this predictor finds no objects (no clustering settings)")
        return scan_instances(
            projection, None, classes, self.profile.things, row_gaps(self.profile), self.clustering
        )

    def scan_prediction(
        self,
        projection: Projection,
        classes: np.ndarray,
        confidence: np.ndarray | None = None,
        times: StageTimes | None = None,
    ) -> ScanOutcome:
        """One scan's prediction from its final classes: what its file holds (with panoptic
        segmentation, the layout's panoptic labels of its objects), or why it has none (more
        objects than its benchmark's label holds)."""
        raw = self.to_raw(classes)
        if self.clustering is None:
            return ScanPrediction(labels=raw, classes=classes, confidence=confidence)
        with self._record(times).stage("cluster"):
            instances = self.instances(projection, classes)
        try:
            labels = self.profile.layout.panoptic_encoding.encode(raw, instances, classes)
        except PanopticEncodingError as exc:
            return str(exc)
        return ScanPrediction(labels, confidence, classes, instances)

    # Whole scans ---------------------------------------------------------------------------

    def predict(self, points: np.ndarray) -> ScanPrediction:
        """Raw labels, one per point, for one (N, 4) scan (a scan that cannot be projected raises
        the `ValueError` of `project`)."""
        (result,) = self.label_projections([self.project(points)])
        if isinstance(result, str):  # a projected scan always has a prediction
            raise ValueError(result)
        return result

    def label_projections(
        self,
        scans: Sequence[Projection | str],
        times: StageTimes | None = None,
        *,
        with_confidence: bool = False,
    ) -> list[ScanOutcome]:
        """Stages 2 to 4 for a batch: a prediction for each projected scan and, for a scan given
        as the reason it has no projection, that reason, in order; with `with_confidence`, each
        point's confidence in its label too. Every runner's path from projection to raw labels.

        The network runs once on the projected scans, one batch at a time whatever the thread;
        its own failures (out of device memory, say) raise: they are the runner's to report.
        """
        good = [s for s in scans if not isinstance(s, str)]
        if not good:
            return list(scans)
        with self._lock:
            logits = self.logits(good, times)
            classes = self.refine_batch(good, logits, times)
            confidences: list[np.ndarray | None] = [None] * len(good)
            if with_confidence:
                confidences = point_confidences(
                    logits, [p.proj_x for p in good], [p.proj_y for p in good], classes
                )
        done = iter(
            self.scan_prediction(projection, c, conf, times)
            for projection, c, conf in zip(good, classes, confidences, strict=True)
        )
        return [s if isinstance(s, str) else next(done) for s in scans]

    # Internals -----------------------------------------------------------------------------

    @staticmethod
    def _record(times: StageTimes | None) -> StageTimes:
        return StageTimes() if times is None else times

    def _forward(self, batch: torch.Tensor) -> torch.Tensor:
        if self.onnx is not None:
            return self.onnx(batch)
        if self.graph is not None:  # its dtype is its own; fp32 keeps TF32 off on CUDA
            with forward_precision("fp32", self.device):
                return self.graph(batch)
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
