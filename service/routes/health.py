"""/healthz and /metrics: the state of the gateway and its workers, for probes and Prometheus.

Neither needs the bearer token, so probes and scrapers work without it.
"""

from __future__ import annotations

import asyncio

from fastapi import APIRouter
from fastapi.responses import JSONResponse, Response

from service.dependencies import GatewayDep
from service.schemas import Health

router = APIRouter()


@router.get(
    "/healthz",
    summary="Health of the gateway and its workers",
    response_model=Health,
    responses={503: {"model": Health, "description": "The worker backend is unavailable"}},
)
async def healthz(gw: GatewayDep) -> JSONResponse:
    state = await asyncio.to_thread(gw.pool.health)
    ok = bool(state.get("ok"))
    workers = state.get("actors", [])
    precisions = sorted({w["precision"] for w in workers if w.get("precision")})
    body = Health(
        status="ok" if ok else "unavailable",
        backend=state.get("backend", gw.pool.backend),
        profile=gw.profile.name,
        point_fields=list(gw.profile.points.fields),
        workers=workers,
        precision=", ".join(precisions) or None,
        queue_depth=gw.batcher.depth() if gw.batcher else 0,
        batch_size=gw.settings.batch_size,
        batch_wait_ms=gw.settings.batch_wait_ms,
        checkpoint_sha256=gw.checkpoint_sha256,
        error=state.get("error"),
    )
    return JSONResponse(body.model_dump(mode="json"), status_code=200 if ok else 503)


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={
        200: {
            "description": "Prometheus text exposition",
            "content": {"text/plain": {"schema": {"type": "string"}}},
        }
    },
)
async def metrics(gw: GatewayDep) -> Response:
    depth = gw.batcher.depth() if gw.batcher else 0
    counts = await asyncio.to_thread(gw.jobs.store.counts) if gw.jobs else {}
    return Response(gw.metrics.render(depth, counts), media_type=gw.metrics.content_type)
