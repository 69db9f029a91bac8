"""Response bodies of the HTTP API that describe the gateway itself, with OpenAPI examples: its
health, the profile it serves and its models (`service.schemas` holds the scans' and jobs')."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


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
                    "precision_reason": "asked for (fp32 is the default); auto would pick bf16 "
                    "here: this CPU has AMX bf16 (amx_bf16)",
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
    precision_reason: str | None = Field(
        None,
        description="why the workers run at that precision: what `--precision auto` picks on "
        "this machine and why, or that another was asked for (one clause per precision, "
        "`fp32: ...; bf16: ...`, where the workers run at several)",
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


class PanopticLabels(BaseModel):
    """How a profile's panoptic labels (`panoptic=true`) pack a point's label and its object:
    `instance * multiplier + label` where `instance_high` (SemanticKITTI), else
    `label * multiplier + instance` (nuScenes-panoptic)."""

    benchmark: str | None = Field(
        description="the profile's panoptic benchmark, whose archive a panoptic job's zip is "
        "(null: none, the predictions tree's files)"
    )
    things: list[str] = Field(description="the thing classes, whose points form objects")
    label_bytes: int = Field(
        gt=0,
        description="bytes per label (little-endian unsigned) of a panoptic raw answer: 4 for "
        "SemanticKITTI's `.label`, 2 for nuScenes-panoptic's uint16",
    )
    multiplier: int = Field(gt=1, description="65536 (SemanticKITTI) or 1000 (nuScenes)")
    instance_high: bool = Field(
        description="whether the instance is the label's high part (SemanticKITTI) rather than "
        "its low part (nuScenes, where instances are numbered within their class)"
    )


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
    panoptic: PanopticLabels | None = Field(
        default=None,
        description="how `panoptic=true` answers pack each point's object into its label; null "
        "where the profile names no thing classes (`panoptic=true` is refused)",
    )


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
                    "precision": "bf16",
                    "precision_reason": "auto's pick here: this CPU has AMX bf16 (amx_bf16)",
                },
                {
                    "id": "kitti",
                    "name": "rangeret-thesis",
                    "checkpoint_sha256": "4c07...",
                    "profile": "semantickitti",
                    "demo_weights": True,
                    "note": "Demo weights: trained on simulated scenes only, so their labels of "
                    "real scans are not meaningful. Serve real weights with rangeret serve "
                    "--checkpoint rangeret-kitti-657 (`rangeret weights list`).",
                    "precision": "fp32",
                    "precision_reason": "asked for (fp32 is the default); auto would pick bf16 "
                    "here: NVIDIA H200 runs bf16 natively",
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
    precision: str | None = Field(
        default=None,
        description="the precision of the model's forward pass (fp32, fp16 or bf16), its "
        "--precision resolved on this machine; null where the Serve application runs it",
    )
    precision_reason: str | None = Field(
        default=None,
        description="why: what `--precision auto` picks on this machine and why, or that "
        "another was asked for",
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
