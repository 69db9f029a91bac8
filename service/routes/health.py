"""/healthz and /metrics: the state of the gateway and its workers, for probes and Prometheus.

Neither needs the bearer token, so probes and scrapers work without it. Without the token,
`/healthz` says only whether the gateway is up and what it serves (model, profile, version); the
details (workers, their processes and checkpoint, the precision and why it is the one, queue,
batching) need the token where one is set, as the /v1 endpoints do.
"""

from __future__ import annotations

import asyncio
from importlib.metadata import PackageNotFoundError, version
from typing import Annotated, Any

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials

from rangeret.inference.runtime.precision import precision_reason
from service.http.dependencies import BEARER, GatewayDep, token_matches
from service.http.errors import error_responses
from service.served_schemas import Health, HealthSummary

router = APIRouter(tags=["service"])


def software_version() -> str:
    """The installed gateway's version ("unknown" when it runs from an uninstalled tree)."""
    try:
        return version("rangeret-service")
    except PackageNotFoundError:
        return "unknown"


def with_precision_reason(worker: dict[str, Any]) -> dict[str, Any]:
    """A worker's description with why it runs at its precision (`precision_reason`), where it
    names its precision and device: the workers that describe themselves so run in this process,
    on this machine."""
    precision, device = worker.get("precision"), worker.get("device")
    if not precision or not device or "precision_reason" in worker:
        return worker
    backend = worker.get("backend", "torch")
    return {**worker, "precision_reason": precision_reason(precision, device, backend)}


def precision_reasons(workers: list[dict[str, Any]]) -> str | None:
    """Why the workers run at their precision: the one reason, or `fp32: ...; bf16: ...` where
    they run at several; None where no worker says."""
    reasons = {
        (w["precision"], w["precision_reason"]) for w in workers if w.get("precision_reason")
    }
    if len(reasons) <= 1:
        return next((reason for _, reason in reasons), None)
    return "; ".join(f"{precision}: {reason}" for precision, reason in sorted(reasons))


@router.get(
    "/healthz",
    summary="Health of the gateway and its workers",
    description=(
        "Without the token (where the gateway has one): status, model, profile and version only. "
        "With it, or on a gateway without a token: the workers, precision (and why), queue and "
        "batching too."
    ),
    operation_id="health",
    response_model=Health | HealthSummary,
    responses={
        503: {"model": Health | HealthSummary, "description": "The worker backend is unavailable"}
    },
)
async def healthz(
    gw: GatewayDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)],
) -> JSONResponse:
    state = await gw.labeller.health()
    ok = bool(state.get("ok"))
    workers = state.get("workers", [])
    default = gw.models.default_entry
    model = default.network or next((w["model"] for w in workers if w.get("model")), None)
    summary = HealthSummary(
        status="ok" if ok else "unavailable",
        model=model,
        profile=default.profile.name,
        models={entry.name: entry.profile.name for entry in gw.models},
        version=software_version(),
    )
    status_code = 200 if ok else 503
    if gw.settings.token is not None and not token_matches(gw, credentials):
        return JSONResponse(summary.model_dump(mode="json"), status_code=status_code)
    workers = [with_precision_reason(w) for w in workers]
    precisions = sorted({w["precision"] for w in workers if w.get("precision")})
    body = Health(
        **summary.model_dump(),
        backend=state.get("backend", gw.labeller.backend),
        point_fields=list(gw.profile.points.fields),
        workers=workers,
        precision=", ".join(precisions) or None,
        precision_reason=precision_reasons(workers),
        queue_depth=gw.labeller.depth(),
        batch_size=gw.settings.batch_size,
        batch_wait_ms=gw.settings.batch_wait_ms,
        checkpoint_sha256=gw.checkpoint_sha256,
        error=state.get("error"),
    )
    return JSONResponse(body.model_dump(mode="json"), status_code=status_code)


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    operation_id="get_metrics",
    response_class=Response,
    responses={
        200: {
            "description": "Prometheus text exposition",
            "content": {"text/plain": {"schema": {"type": "string"}}},
        },
        **error_responses(400),
    },
)
async def metrics(gw: GatewayDep) -> Response:
    depth = gw.labeller.depth()
    counts = await asyncio.to_thread(gw.jobs.store.counts) if gw.jobs else {}
    in_process = gw.loaded_models()
    loaded = None if in_process is None else {m: m in in_process for m in gw.models.names}
    return Response(gw.metrics.render(depth, counts, loaded), media_type=gw.metrics.content_type)
