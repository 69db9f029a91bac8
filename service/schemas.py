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


class ScanObject(BaseModel):
    """One object of a panoptic answer: its instance id, its class and its points."""

    instance: int = Field(ge=1, description="the object's id in `instances`, unique in the scan")
    class_name: str = Field(description="the object's class, a thing class of the profile")
    points: int = Field(ge=1, description="the object's points")


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
                },
                {
                    "model": "default",
                    "num_points": 4,
                    "labels": [40, 40, 65546, 70],
                    "class_counts": {"car": 1, "road": 2, "vegetation": 1},
                    "instances": [0, 0, 1, 0],
                    "objects": [{"instance": 1, "class_name": "car", "points": 1}],
                },
            ]
        }
    )

    model: str = Field(description="the model that labelled the scan")
    num_points: int = Field(ge=0, description="points in the scan, and labels in `labels`")
    labels: list[int] = Field(
        description="every point's label as the model's profile's prediction files hold it, in "
        "the scan's point order: the raw id of its label configuration (SemanticKITTI), or the "
        "class index itself (nuScenes' challenge classes 1-16); with `panoptic=true`, the "
        "panoptic label of its benchmark (SemanticKITTI: `instance << 16 | raw id`; nuScenes: "
        "`1000 * class + instance`, the instance numbered within its class)"
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
    instances: list[int] | None = Field(
        default=None,
        description="with `panoptic=true`: each point's object, an id unique in the scan (0 for "
        "a point of a stuff class, or of no object), in the scan's point order",
    )
    objects: list[ScanObject] | None = Field(
        default=None,
        description="with `panoptic=true`: every object, by instance id, with its class and points",
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
                {"dataset": "/data/semantickitti", "split": "valid", "panoptic": True},
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
    panoptic: bool = Field(
        default=False,
        description="panoptic segmentation: also find the objects of the thing classes, the "
        "predictions written as `rangeret predict --panoptic` writes them, zipped as the "
        "profile's panoptic benchmark wants them and evaluated as it scores them; refused for a "
        "model whose profile names no thing classes",
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
    pq: float | None = Field(
        default=None,
        ge=0,
        le=1,
        description="a panoptic job's panoptic quality, the mean over the evaluated classes "
        "(null for other jobs)",
    )
    sq: float | None = Field(
        default=None, ge=0, le=1, description="a panoptic job's segmentation quality"
    )
    rq: float | None = Field(
        default=None, ge=0, le=1, description="a panoptic job's recognition quality"
    )
    pq_dagger: float | None = Field(
        default=None,
        ge=0,
        le=1,
        description="a panoptic job's PQ-dagger: PQ of the thing classes, IoU of the stuff ones",
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
    panoptic: bool = Field(
        default=False,
        description="whether the job finds objects too (panoptic segmentation): its predictions "
        "are the benchmark's panoptic labels, its zip the panoptic benchmark's and its report "
        "the panoptic scores",
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
