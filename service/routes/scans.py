"""POST /v1/scans: label one scan, answered as raw `.label` bytes or, when asked for, as JSON.

The body holds the served profile's point records (SemanticKITTI: x, y, z, remission, 16 bytes per
point; PandaSet adds the laser id, 20 bytes); the labels are raw ids of its label configuration.
"""

from __future__ import annotations

import asyncio

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, Response

from rangeret.dataset.labels import LabelConfig
from rangeret.io.scans import ScanFormatError, parse_scan
from service.admission import RETRY_AFTER_S, QueueFull
from service.batching import BackendError, BackendTimeout, ScanRejected
from service.dependencies import GatewayDep
from service.errors import ApiError, error_responses
from service.gateway import Gateway
from service.schemas import BINARY_CONTENT, ScanLabels
from service.uploads import declared_length, drain, media_type, read_body

OCTET = "application/octet-stream"

router = APIRouter(prefix="/v1")


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


def _class_counts(labels: np.ndarray, config: LabelConfig) -> dict[str, int]:
    counts = np.bincount(config.to_class(labels), minlength=config.num_classes)
    return {config.class_names[c]: int(n) for c, n in enumerate(counts) if n}


@router.post(
    "/scans",
    summary="Label one scan",
    description=(
        "The body is the raw bytes of one `.bin` scan in the served profile's point record "
        "(`/healthz` names the profile and its point fields: SemanticKITTI's are float32 x, y, z, "
        "remission, PandaSet's add laser_id). The answer is the raw `.label` bytes (uint32 raw "
        "ids of the profile's label configuration, one per point), or with "
        "`Accept: application/json` the labels with their class counts. Concurrent requests are "
        "labelled together in batches."
    ),
    response_class=Response,
    responses={
        200: {
            "description": "One raw label per point",
            "content": {
                OCTET: BINARY_CONTENT,
                "application/json": {"schema": ScanLabels.model_json_schema()},
            },
        },
        **error_responses(400, 408, 413, 415, 503, 504),
    },
    openapi_extra={"requestBody": {"required": True, "content": {OCTET: BINARY_CONTENT}}},
)
async def label_scan(
    request: Request,
    gw: GatewayDep,
    knn: bool = Query(default=True, description="refine labels with kNN over the point cloud"),
    confidence: bool = Query(
        default=False,
        description="also return each point's confidence (the softmax probability of its label "
        "at its pixel); needs `Accept: application/json`",
    ),
) -> Response:
    limits = gw.settings
    if confidence and not wants_json(request.headers.get("accept")):
        await drain(request, limits.max_body_bytes, timeout=limits.body_timeout_s)
        raise ApiError(
            400,
            "Confidences come only in the JSON answer: send 'Accept: application/json' with "
            "confidence=true, or leave confidence out for the raw label bytes.",
        )
    if media_type(request) != OCTET:
        await drain(request, limits.max_body_bytes, timeout=limits.body_timeout_s)
        raise ApiError(
            415,
            f"Send the scan as {OCTET}; "
            + (
                f"this request's Content-Type is {media_type(request)[:100]}."
                if media_type(request)
                else "this request has no Content-Type."
            ),
        )
    declared = declared_length(request)
    try:
        reserve = (
            limits.max_body_bytes if declared is None else min(declared, limits.max_body_bytes)
        )
        place = gw.admission.admit(reserve)
    except QueueFull as exc:
        await drain(request, limits.max_body_bytes, timeout=limits.body_timeout_s)
        gw.metrics.refused.inc()
        raise ApiError(503, str(exc), {"Retry-After": str(RETRY_AFTER_S)}) from exc
    with place:
        return await _label(request, gw, knn, confidence)


async def _label(request: Request, gw: Gateway, knn: bool, confidence: bool) -> Response:
    """Read, check and label an admitted scan, and answer in the form the client asked for."""
    limits = gw.settings
    body = await read_body(request, limits.max_body_bytes, timeout=limits.body_timeout_s)
    record = gw.profile.points
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
            f"{', '.join(record.fields)}, the point record of the {gw.profile.name} profile).",
        )
    try:
        points = await asyncio.to_thread(parse_scan, body, "the scan", record=record)
    except ScanFormatError as exc:
        raise ApiError(400, f"The scan is malformed: {exc.problem}.") from exc
    if not gw.started:
        raise ApiError(503, "The gateway is starting; try again in a moment.")
    try:
        labelled = await gw.labeller.label(points, body, knn, confidence)
    except ScanRejected as exc:
        raise ApiError(400, f"The scan cannot be projected: {exc}.") from exc
    except BackendTimeout as exc:
        raise ApiError(504, _sentence(exc)) from exc
    except BackendError as exc:
        raise ApiError(503, _sentence(exc), {"Retry-After": str(RETRY_AFTER_S)}) from exc
    gw.metrics.scans.labels(source="request").inc()
    gw.metrics.points.inc(len(points))
    raw = labelled.labels.astype("<u4", copy=False)
    if wants_json(request.headers.get("accept")):
        body = ScanLabels(
            num_points=len(raw),
            labels=raw.tolist(),
            class_counts=_class_counts(raw, gw.profile.labels),
            confidence=None
            if labelled.confidence is None
            else np.round(labelled.confidence, 4).tolist(),
        )
        return JSONResponse(body.model_dump(exclude_none=True))
    return Response(raw.tobytes(), media_type=OCTET)


def _sentence(exc: Exception) -> str:
    """A backend failure as the answer's sentence."""
    text = str(exc)
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")
