"""POST /v1/scans: label one scan, answered as raw `.label` bytes or, when asked for, as JSON.

The body holds the served profile's point records (SemanticKITTI: x, y, z, remission, 16 bytes per
point; PandaSet adds the laser id, 20 bytes; nuScenes' `.pcd.bin` the ring), or a PCD, PLY, LAS
or LAZ file (`service.labelling.scan_bodies`); the labels are what the profile's prediction files hold
(raw ids of its label configuration, or nuScenes' challenge classes), one per point in the
body's order, and the raw answer is as wide as those files' labels (4 bytes, nuScenes' 1). The answer's form is chosen with `?format=json` (or `raw`), else by the
`Accept` header. With `?panoptic=true` the labels are the benchmark's panoptic labels of the
scan's objects (`service.labelling.panoptic`), as `rangeret predict --panoptic` writes them, the
JSON answer adds each point's object, and `X-RangeRet-Instances` counts the objects.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response

from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.clouds import spread_labels
from rangeret.inference.results import ScanPrediction
from rangeret.io.scans import ScanFormatError, parse_scan
from service.gateway import Gateway
from service.http.bodies import declared_length, media_type, read_body, refused_body
from service.http.dependencies import GatewayDep
from service.http.errors import ApiError, error_responses
from service.labelling.admission import RETRY_AFTER_S, QueueFull
from service.labelling.errors import BackendError, BackendTimeout, ScanRejected
from service.labelling.panoptic import (
    INSTANCES_HEADER,
    label_classes,
    panoptic_dtype,
    panoptic_refusal,
    scan_objects,
)
from service.labelling.scan_bodies import (
    CONTENT_TYPES,
    OCTET,
    FileBody,
    body_format,
    body_limits,
    decode_file_body,
)
from service.models.catalog import MODEL_HEADER, MODEL_QUERY, ModelEntry
from service.schemas import BINARY_CONTENT, LabelFormat, ScanLabels, ScanObject

router = APIRouter(prefix="/v1", tags=["scans"])


def wants_json(accept: str | None) -> bool:
    """Whether the Accept header prefers application/json to the raw label bytes."""
    if not accept:
        return False
    weights: dict[str, float] = {}
    for item in accept.split(","):
        kind, *params = (p.strip() for p in item.split(";"))
        q = 1.0
        for param in params:
            if param.lower().startswith("q="):
                try:
                    q = float(param[2:])
                except ValueError:
                    q = 0.0
        weights[kind.lower()] = max(q, weights.get(kind.lower(), 0.0))
    as_json = weights.get("application/json", 0.0)
    if as_json <= 0:
        return False
    if OCTET not in weights:
        return True
    return as_json > weights[OCTET]


def json_answer(form: LabelFormat | None, accept: str | None) -> bool:
    """Whether to answer in JSON: as the `format` query says where it is given, else as the
    `Accept` header prefers."""
    if form is not None:
        return form is LabelFormat.json
    return wants_json(accept)


def _class_counts(classes: np.ndarray, profile: DatasetProfile) -> dict[str, int]:
    """Points per class name of the profile's training classes."""
    names = profile.labels.class_names
    counts = np.bincount(classes, minlength=len(names))
    return {names[c]: int(n) for c, n in enumerate(counts) if n}


@router.post(
    "/scans",
    summary="Label one scan",
    description=(
        "The body is the raw bytes of one `.bin` scan in the served profile's point record "
        "(`/healthz` names the profile and its point fields: SemanticKITTI's are float32 x, y, z, "
        "remission, PandaSet's add laser_id), or a point-cloud file: PCD (`application/x-pcd`), "
        "PLY (`application/x-ply` or `application/ply`), LAS (`application/vnd.las`) or LAZ "
        "(`application/vnd.laszip`); an `application/octet-stream` body that starts with a PCD, "
        "PLY or LAS signature is read as that file. A file whose header declares more points than "
        "RANGERET_MAX_POINTS, or more than RANGERET_MAX_DECODED_BYTES once decoded, is refused "
        "with 413 before it is decoded. The answer is the bytes of the profile's "
        "label file, one label per point in the body's order (a `.label` file's uint32 raw ids "
        "of its label configuration; for nuScenes, a `_lidarseg.bin` file's uint8 challenge "
        "classes; a file's points with a NaN or infinite value get the unlabelled raw id), or "
        "with `format=json` (or, without `format`, `Accept: application/json`) the labels with "
        "their class counts. With `panoptic=true` the thing classes' points are also "
        "clustered into objects, as `rangeret predict --panoptic` clusters them: the labels are "
        "the profile's panoptic benchmark's (SemanticKITTI: uint32 `instance << 16 | raw id`; "
        "nuScenes: uint16 `1000 * class + instance`), the JSON answer adds every point's "
        "object (`instances`) and the objects, and the `X-RangeRet-Instances` header counts "
        "them. Concurrent requests are labelled together in batches."
    ),
    operation_id="label_scan",
    response_class=Response,
    responses={
        200: {
            "description": "One label per point as the profile's label files hold it (the JSON "
            "form with `format=json`)",
            "headers": {
                INSTANCES_HEADER: {
                    "description": "with `panoptic=true`: how many objects the scan holds",
                    "schema": {"type": "integer", "minimum": 0},
                }
            },
            "content": {
                OCTET: BINARY_CONTENT,
                "application/json": {"schema": {"$ref": "#/components/schemas/ScanLabels"}},
            },
        },
        **error_responses(
            400,
            403,
            404,
            408,
            413,
            415,
            503,
            504,
            described={
                400: "Malformed scan or query, `panoptic=true` for a model whose profile "
                "names no thing classes, or a Host the gateway does not answer to",
                404: "No model of that name",
                503: "The single-scan queue is full (with Retry-After), the labelling backend "
                "is unavailable, or the gateway is starting",
            },
        ),
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {kind: BINARY_CONTENT for kind in CONTENT_TYPES},
        }
    },
)
async def label_scan(
    request: Request,
    gw: GatewayDep,
    knn: bool = Query(default=True, description="refine labels with kNN over the point cloud"),
    confidence: bool = Query(
        default=False,
        description="also return each point's confidence (the softmax probability of its label "
        "at its pixel); needs the JSON answer",
    ),
    panoptic: bool = Query(
        default=False,
        description="also find the objects of the thing classes: the labels are the profile's "
        "panoptic labels, the JSON answer adds every point's object, and the "
        "`X-RangeRet-Instances` header counts the objects",
    ),
    form: Annotated[
        LabelFormat | None,
        Query(
            alias="format",
            description="the answer's form: `raw` label bytes or `json`; without it, the "
            "`Accept` header chooses (raw bytes unless it prefers application/json)",
        ),
    ] = None,
    model: Annotated[str | None, MODEL_QUERY] = None,
) -> Response:
    limits = gw.settings
    try:
        entry = gw.models.get(model)
    except ApiError as exc:
        raise await refused_body(request, limits, exc) from None
    refusal = panoptic_refusal(entry.profile, entry.name) if panoptic else None
    if refusal is not None:
        raise await refused_body(request, limits, ApiError(400, refusal))
    as_json = json_answer(form, request.headers.get("accept"))
    if confidence and not as_json:
        refusal = ApiError(
            400,
            "Confidences come only in the JSON answer: send format=json (or 'Accept: "
            "application/json') with confidence=true, or leave confidence out for the raw label "
            "bytes.",
        )
        raise await refused_body(request, limits, refusal)
    if media_type(request) not in CONTENT_TYPES:
        given = media_type(request)[:100]
        refusal = ApiError(
            415,
            f"Send the scan as {', '.join(CONTENT_TYPES)}; "
            + (
                f"this request's Content-Type is {given}."
                if given
                else "this request has no Content-Type."
            ),
        )
        raise await refused_body(request, limits, refusal)
    declared = declared_length(request)
    try:
        reserve = (
            limits.max_body_bytes if declared is None else min(declared, limits.max_body_bytes)
        )
        place = gw.admission.admit(reserve)
    except QueueFull as exc:
        gw.metrics.refused.inc()
        busy = ApiError(503, str(exc), {"Retry-After": str(RETRY_AFTER_S)})
        raise await refused_body(request, limits, busy) from exc
    with place:
        asked = _Asked(knn, confidence, panoptic, as_json)
        return await _label(request, gw, entry, asked)


@dataclass(frozen=True)
class _Asked:
    """How a request wants its scan labelled and answered."""

    knn: bool
    confidence: bool
    panoptic: bool
    as_json: bool


async def _label(request: Request, gw: Gateway, entry: ModelEntry, asked: _Asked) -> Response:
    """Read, check and label an admitted scan with the model `entry`, and answer in the form
    the client asked for."""
    limits = gw.settings
    body = await read_body(request, limits.max_body_bytes, timeout=limits.body_timeout_s)
    fmt = body_format(media_type(request), body[:16])
    if fmt != "bin":
        return await _label_file(gw, entry, body, fmt, asked)
    profile = entry.profile
    record = profile.points
    if len(body) // record.point_bytes > limits.max_points:
        raise ApiError(
            413,
            f"The scan has {len(body) // record.point_bytes:,} points, over the limit of "
            f"{limits.max_points:,}.",
        )
    if len(body) % record.point_bytes:
        raise ApiError(
            400,
            f"The scan is malformed: size {len(body)} bytes is not a multiple of "
            f"{record.point_bytes} ({record.point_bytes} bytes per point: "
            f"{', '.join(record.fields)}, the point record of the {profile.name} profile).",
        )
    try:
        points = await asyncio.to_thread(parse_scan, body, "the scan", record=record)
    except ScanFormatError as exc:
        raise ApiError(400, f"The scan is malformed: {exc.problem}.") from exc
    labelled = await _labelled(gw, entry, points, asked)
    return _answer(entry, labelled, asked)


async def _label_file(
    gw: Gateway, entry: ModelEntry, body: bytes, fmt: str, asked: _Asked
) -> Response:
    """Label a PCD, PLY, LAS or LAZ body: its header checked against the limits and the body
    decoded off the event loop, its valid points labelled, the answer one label per point of the
    body (an invalid point is in no object)."""
    profile = entry.profile
    limits = body_limits(gw.settings)
    decoded: FileBody = await asyncio.to_thread(decode_file_body, body, fmt, profile, limits)
    if len(decoded.points):
        labelled = await _labelled(gw, entry, decoded.points, asked)
    else:
        none = np.zeros(0, dtype=np.uint32)
        labelled = ScanPrediction(
            none,
            np.zeros(0, dtype=np.float32) if asked.confidence else None,
            instances=none if asked.panoptic else None,
        )
    every = spread_labels(
        decoded.valid,
        labelled.labels,
        labelled.confidence,
        config=profile.labels,
        instances=labelled.instances,
    )
    if not asked.confidence:
        every.confidence = None
    return _answer(entry, every, asked)


async def _labelled(
    gw: Gateway, entry: ModelEntry, points: np.ndarray, asked: _Asked
) -> ScanPrediction:
    """The labeller's answer for checked points, its failures as the HTTP errors they mean."""
    if not gw.started:
        raise ApiError(503, "The gateway is starting; try again in a moment.")
    try:
        labelled = await gw.labeller.label_points(
            points, asked.knn, asked.confidence, asked.panoptic, model=entry.name
        )
    except ScanRejected as exc:
        if asked.panoptic:
            raise ApiError(400, f"The scan cannot be labelled with its objects: {exc}.") from exc
        raise ApiError(400, f"The scan cannot be projected: {exc}.") from exc
    except BackendTimeout as exc:
        raise ApiError(504, _sentence(exc)) from exc
    except BackendError as exc:
        raise ApiError(503, _sentence(exc), {"Retry-After": str(RETRY_AFTER_S)}) from exc
    gw.metrics.scans.labels(source="request", model=entry.name).inc()
    gw.metrics.points.labels(model=entry.name).inc(len(points))
    return labelled


def _answer(entry: ModelEntry, labelled: ScanPrediction, asked: _Asked) -> Response:
    """The label bytes as wide as the profile's label files hold them (a `.label` file's, a
    nuScenes `_lidarseg.bin`'s; with `panoptic`, its panoptic benchmark's), or the JSON answer
    when the client asked for it; either names the model in its `X-RangeRet-Model` header and,
    with `panoptic`, counts the objects in `X-RangeRet-Instances`."""
    profile = entry.profile
    dtype = panoptic_dtype(profile) if asked.panoptic else profile.layout.label_file.dtype
    raw = labelled.labels.astype(dtype, copy=False)
    headers = {MODEL_HEADER: entry.name}
    instances = labelled.instances if asked.panoptic else None
    if instances is not None:
        headers[INSTANCES_HEADER] = str(labelled.num_instances)
    if not asked.as_json:
        return Response(raw.tobytes(), media_type=OCTET, headers=headers)
    classes = label_classes(profile, raw, asked.panoptic)
    confidence = labelled.confidence
    body = ScanLabels(
        model=entry.name,
        num_points=len(raw),
        labels=raw.tolist(),
        class_counts=_class_counts(classes, profile),
        confidence=None if confidence is None else np.round(confidence, 4).tolist(),
        instances=None if instances is None else instances.tolist(),
        objects=None
        if instances is None
        else [
            ScanObject(instance=i, class_name=name, points=n)
            for i, name, n in scan_objects(profile, classes, instances)
        ],
    )
    return JSONResponse(body.model_dump(exclude_none=True), headers=headers)


def _sentence(exc: Exception) -> str:
    """A backend failure as the answer's sentence."""
    text = str(exc)
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")
