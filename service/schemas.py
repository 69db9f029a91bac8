"""Request and response bodies of the HTTP API, with OpenAPI examples."""

from __future__ import annotations

import re
from datetime import datetime
from enum import Enum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

SEQUENCE_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
#: A tables layout's version: the name of its folder of tables (v1.0-mini).
VERSION_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
#: The OpenAPI content of a binary body (a scan, its labels, an archive).
BINARY_CONTENT: dict[str, Any] = {"schema": {"type": "string", "format": "binary"}}
OCTET = "application/octet-stream"
#: The multipart form of an archive upload (`POST /v1/jobs/uploads`), as an OpenAPI schema.
ARCHIVE_UPLOAD: dict[str, Any] = {
    "title": "ArchiveUpload",
    "type": "object",
    "description": "An archive of sequences to predict (and, with labels, to evaluate).",
    "properties": {
        "archive": {
            "type": "string",
            "format": "binary",
            "description": ".zip, .tar or .tar.gz with sequences/XX/velodyne/*.bin (the served "
            "profile's point records) and optional sequences/XX/labels/*.label, whatever the "
            "profile",
        }
    },
    "required": ["archive"],
    "additionalProperties": False,
}


def file_content(media: str) -> dict[str, Any]:
    """The OpenAPI content of a file answer sent as `media`, listed as `application/octet-stream`
    too, so that client generators that do not know `media` still type it as a file."""
    return {media: BINARY_CONTENT, OCTET: BINARY_CONTENT}


class LabelFormat(str, Enum):
    """The form of a labelled scan: raw `.label` bytes, or JSON."""

    raw = "raw"
    json = "json"


class ErrorResponse(BaseModel):
    """Every error answer: one readable sentence."""

    detail: str = Field(
        examples=[
            "The scan is malformed: size 17 bytes is not a multiple of 16 (16 bytes per point: "
            "x, y, z, remission, the point record of the semantickitti profile)."
        ]
    )


class ScanLabels(BaseModel):
    """The JSON form of a labelled scan (asked for with `format=json` or `Accept: application/json`)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "model": "default",
                    "num_points": 4,
                    "labels": [40, 40, 10, 70],
                    "class_counts": {"car": 1, "road": 2, "vegetation": 1},
                }
            ]
        }
    )

    model: str = Field(description="the model that labelled the scan")
    num_points: int = Field(ge=0, description="points in the scan, and labels in `labels`")
    labels: list[int] = Field(
        description="every point's label as the model's profile's prediction files hold it, in "
        "the scan's point order: the raw id of its label configuration (SemanticKITTI), or the "
        "class index itself (nuScenes' challenge classes 1-16)"
    )
    class_counts: dict[str, int] = Field(
        description="points per class name of the model's profile, for the classes present"
    )
    confidence: list[float] | None = Field(
        default=None,
        description="with `confidence=true`: each point's confidence in its label (the softmax "
        "probability of its class at its pixel, 0 to 1; 0 for a point without a pixel), in the "
        "scan's point order",
    )


class DatasetJobRequest(BaseModel):
    """A job over a dataset already on the server, under one of the configured data roots."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"dataset": "/data/semantickitti", "split": "valid"},
                {"dataset": "/data/semantickitti", "sequences": ["08"]},
                {"dataset": "/data/pandaset", "sequences": ["1", "2"], "profile": "pandaset"},
                {"dataset": "/data/pandaset", "sequences": ["1"], "model": "panda"},
                {
                    "dataset": "/data/nuscenes",
                    "split": "val",
                    "version": "v1.0-trainval",
                    "model": "nu",
                },
            ]
        },
    )

    dataset: str = Field(
        min_length=1,
        max_length=4096,
        description="dataset root in the model's profile's layout (SemanticKITTI: "
        "ROOT/sequences/XX, PandaSet: ROOT/NNN, SemanticPOSS: ROOT/dataset/sequences/NN, "
        "nuScenes: ROOT/<version>/*.json with ROOT/samples/LIDAR_TOP); a relative path is taken "
        "under the data roots",
    )
    split: str | None = Field(
        default=None,
        pattern=SEQUENCE_PATTERN,
        description="a split of the model's profile, by its name (SemanticKITTI: train, valid, "
        "test; nuScenes: train, val, test, mini_train, mini_val)",
    )
    version: str | None = Field(
        default=None,
        pattern=VERSION_PATTERN,
        description="for a profile that reads a version's tables (nuScenes): the version folder "
        "to read (v1.0-mini); without it, the one version the dataset holds",
    )
    sequences: list[str] | None = Field(
        default=None,
        min_length=1,
        max_length=1000,
        description="sequence folder names, instead of a split; numeric ones are padded as the "
        "served profile writes them (PandaSet: 1 is 001)",
        json_schema_extra={"items": {"type": "string", "pattern": SEQUENCE_PATTERN}},
    )
    profile: str | None = Field(
        default=None,
        min_length=1,
        max_length=200,
        description="the dataset profile the request is meant for; when given, it must be the "
        "model's",
    )
    model: str | None = Field(
        default=None,
        min_length=1,
        max_length=63,
        description="the served model to run (`GET /v1/models`); without it, the default model",
    )

    @model_validator(mode="after")
    def _one_selection(self) -> DatasetJobRequest:
        """Exactly one of `split` and `sequences`, and sequence names that are plain folder names."""
        if (self.split is None) == (self.sequences is None):
            raise ValueError("give either 'split' or 'sequences', not both and not neither")
        for name in self.sequences or ():
            if not re.fullmatch(SEQUENCE_PATTERN, name):
                raise ValueError(f"sequence name {name[:64]!r} is not a plain folder name")
        return self


class JobState(str, Enum):
    """Where a job is in its life."""

    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"

    @property
    def finished(self) -> bool:
        """Whether the job will not change any more."""
        return self in (JobState.succeeded, JobState.failed, JobState.cancelled)


class JobCreated(BaseModel):
    """The answer to a new job: where to follow it, and its state now (what a poll of
    `status_url` reads until it is final)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "3f2c9a0e5b7d4c1e8f6a2b9d0c4e7f1a",
                    "status_url": "/v1/jobs/3f2c9a0e5b7d4c1e8f6a2b9d0c4e7f1a",
                    "state": "queued",
                }
            ]
        }
    )

    id: str
    status_url: str
    state: JobState = Field(description="the job's state: `queued` until a runner takes it")


class JobMetrics(BaseModel):
    """The headline numbers of a labelled job's evaluation (the full report is at `report_url`)."""

    miou: float = Field(ge=0, le=1)
    accuracy: float = Field(ge=0, le=1)
    iou: dict[str, float | None] = Field(
        description="IoU (0..1) of each evaluated class of the model's profile, by name; null "
        "where nuScenes' scoring leaves a class out (absent from both ground truth and "
        "predictions)"
    )


class JobStatus(BaseModel):
    """A job: its state, progress counts, errors, metrics and where its results are."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "3f2c9a0e5b7d4c1e8f6a2b9d0c4e7f1a",
                    "state": "succeeded",
                    "kind": "archive",
                    "sequences": ["08"],
                    "total": 3,
                    "done": 3,
                    "failed": 0,
                    "metrics": {"miou": 0.41, "accuracy": 0.87, "iou": {"car": 0.9, "road": 0.95}},
                    "errors": [],
                    "reason": None,
                    "created": "2025-01-01T12:00:00Z",
                    "started": "2025-01-01T12:00:01Z",
                    "finished": "2025-01-01T12:00:09Z",
                    "status_url": "/v1/jobs/3f2c9a0e5b7d4c1e8f6a2b9d0c4e7f1a",
                    "predictions_url": "/v1/jobs/3f2c9a0e5b7d4c1e8f6a2b9d0c4e7f1a/predictions",
                    "report_url": "/v1/jobs/3f2c9a0e5b7d4c1e8f6a2b9d0c4e7f1a/report",
                }
            ]
        }
    )

    id: str
    state: JobState
    kind: Literal["archive", "dataset"]
    model: str = Field(description="the served model the job runs with")
    sequences: list[str]
    version: str | None = Field(
        default=None, description="the version a job of a tables profile (nuScenes) reads"
    )
    split: str | None = Field(
        default=None,
        description="the split a dataset job named; a tables profile's predictions are in its "
        "folder (lidarseg/<split>/)",
    )
    total: int = Field(ge=0, description="scans in the job")
    done: int = Field(ge=0, description="scans whose prediction is written")
    failed: int = Field(ge=0, description="scans that could not be predicted (named in `errors`)")
    metrics: JobMetrics | None = Field(
        default=None, description="set when the job's scans had labels"
    )
    errors: list[str] = Field(
        default_factory=list, description="failed scans, each with its reason"
    )
    reason: str | None = Field(default=None, description="why the job failed or was cancelled")
    created: datetime
    started: datetime | None = None
    finished: datetime | None = None
    status_url: str
    predictions_url: str
    report_url: str
    plots: list[str] = Field(
        default_factory=list,
        description="the report's PNGs once a labelled job has succeeded (confusion.png, iou.png, "
        "iou-by-distance.png, miou-by-sequence.png), each at `/v1/jobs/{id}/plots/{name}`",
    )


class JobList(BaseModel):
    """Every job the gateway knows, newest first."""

    jobs: list[JobStatus]


class HealthSummary(BaseModel):
    """What `/healthz` tells a caller without the token: up or not, and what is served."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "status": "ok",
                    "model": "rangeret-cir",
                    "profile": "semantickitti",
                    "version": "0.1.0",
                }
            ]
        }
    )

    status: Literal["ok", "unavailable"]
    model: str | None = Field(description="the default model's network")
    profile: str = Field(description="the default model's dataset profile")
    models: dict[str, str] = Field(
        default_factory=dict, description="every model the gateway serves, with its profile"
    )
    version: str = Field(description="the gateway's software version")


class Health(HealthSummary):
    """The gateway's and its worker backend's state, for callers the token rule lets in."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "status": "ok",
                    "model": "rangeret-cir",
                    "profile": "semantickitti",
                    "version": "0.1.0",
                    "backend": "local",
                    "workers": [{"pid": 4242, "model": "rangeret-cir", "device": "cpu"}],
                    "precision": "fp32",
                    "queue_depth": 0,
                    "batch_size": 4,
                    "batch_wait_ms": 10.0,
                    "checkpoint_sha256": "9b1d...",
                    "point_fields": ["x", "y", "z", "remission"],
                }
            ]
        }
    )

    backend: Literal["local", "serve"] = Field(
        description="where single scans are labelled: in the gateway's process, or on the Serve "
        "application (RANGERET_SERVE_URL)"
    )
    point_fields: list[str] = Field(
        description="the float32 values of one point of a scan, in order (the profile's record)"
    )
    workers: list[dict[str, Any]] = Field(description="one description per model worker")
    precision: str | None = Field(
        None, description="the forward pass precision of the workers (fp32, fp16 or bf16)"
    )
    queue_depth: int = Field(ge=0, description="single-scan requests waiting or in the network")
    batch_size: int
    batch_wait_ms: float
    checkpoint_sha256: str | None = None
    error: str | None = None


class ProfileClass(BaseModel):
    """One training class of the served profile, as the web page draws it."""

    index: int = Field(ge=0, description="the class's index (0 .. classes - 1)")
    name: str
    raw_id: int = Field(ge=0, description="the raw id predictions carry for this class")
    color: str = Field(
        pattern=r"^#[0-9a-f]{6}$",
        description="the class's colour in the profile's palette, as RGB hex (#rrggbb)",
    )
    ignored: bool = Field(description="whether the class is left out of IoU and mIoU")


class ServedProfile(BaseModel):
    """What a client needs to read scans and labels of the served profile and score them."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "profile": "semantickitti",
                    "point_fields": ["x", "y", "z", "remission"],
                    "point_bytes": 16,
                    "label_bytes": 4,
                    "predictions": "raw",
                    "classes": [
                        {
                            "index": 0,
                            "name": "unlabeled",
                            "raw_id": 0,
                            "color": "#000000",
                            "ignored": True,
                        },
                        {
                            "index": 1,
                            "name": "car",
                            "raw_id": 10,
                            "color": "#6496f5",
                            "ignored": False,
                        },
                    ],
                    "raw_to_class": {"0": 0, "1": 0, "10": 1},
                    "unlabeled_class": 0,
                }
            ]
        }
    )

    profile: str = Field(description="the served dataset profile's name")
    point_fields: list[str] = Field(description="the float32 values of one point, in order")
    point_bytes: int = Field(gt=0, description="bytes per point of a scan")
    label_bytes: int = Field(
        default=4,
        gt=0,
        description="bytes per label (little-endian unsigned) of the profile's label and "
        "prediction files, and of a scan's raw answer: 4 for a `.label` file, 1 for nuScenes' "
        "`_lidarseg.bin`",
    )
    predictions: Literal["raw", "class"] = Field(
        default="raw",
        description="what a prediction's labels are: `raw` ids of the label configuration "
        "(`raw_to_class` maps them), or the `class` indices themselves (nuScenes' challenge "
        "classes; its ground truth files hold raw ids)",
    )
    classes: list[ProfileClass] = Field(description="the training classes, by index")
    raw_to_class: dict[str, int] = Field(
        description="the class index of every raw id of the label configuration (its learning "
        "map); a raw id not listed, after masking it to its low 16 bits, is the unlabeled class"
    )
    unlabeled_class: int = Field(ge=0, description="the class of raw ids the map does not list")


class ServedModel(BaseModel):
    """The network the gateway serves: its name, its checkpoint and whether it is the demo's."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "default",
                    "name": "rangeret-cir",
                    "checkpoint_sha256": "9b1d...",
                    "profile": "semantickitti",
                    "demo_weights": False,
                    "note": None,
                },
                {
                    "id": "kitti",
                    "name": "rangeret-thesis",
                    "checkpoint_sha256": "4c07...",
                    "profile": "semantickitti",
                    "demo_weights": True,
                    "note": "Demo weights: trained on simulated scenes only, so their labels of "
                    "real scans are not meaningful. Serve a published model with rangeret serve "
                    "--checkpoint rangeret-kitti-657 (see rangeret weights list).",
                },
            ]
        }
    )

    id: str = Field(description="the model's name in this gateway (`?model=`, a job's `model`)")
    name: str | None = Field(description="the served network (rangeret-cir, rangeret-thesis)")
    checkpoint_sha256: str | None = Field(
        description="SHA-256 of the checkpoint file the gateway loaded"
    )
    profile: str = Field(description="the dataset profile the model runs with")
    demo_weights: bool = Field(
        description="whether the checkpoint is the bundled demo weights, trained on simulated "
        "scenes only: their labels of real scans are not meaningful"
    )
    note: str | None = Field(
        default=None,
        description="with the demo weights: what they are and how to serve a published model "
        "instead (one or two sentences, for a page to show beside the model's name)",
    )


class ListedModel(ServedModel):
    """One model of `GET /v1/models`: what `GET /v1/model` says of it, and whether its network
    is loaded in the gateway's process now."""

    loaded: bool = Field(
        description="whether the network is loaded now (on a Serve application: always true)"
    )


class ModelList(BaseModel):
    """The models a gateway serves, in its models file's order, and the default one."""

    default: str = Field(description="the model a request that names none gets")
    models: list[ListedModel]
