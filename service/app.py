"""The FastAPI app of the gateway: `create_app`, its lifespan and its OpenAPI document.

`create_app` takes the settings, a single-scan labeller, a job executor and the dataset profile of
the served network, and builds the `Gateway` (`service.gateway`) that owns the labeller, the job
store and runner, and the metrics. The endpoints are in `service.routes` (one module per
resource), the error answers in `service.http.error_handlers`: every error is
`{"detail": "<one sentence>"}`. With RANGERET_API_TOKEN set, every /v1 request needs
`Authorization: Bearer TOKEN` (/metrics and the API description do not; /healthz gives its details only with it).
The API description is the same whether or not a token is set, with stable operation ids, one
request body per operation and every error answer described, so client generators can use it.
The web page at `/` (`service.routes.page`) needs no token itself and sends it on its API calls.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic import BaseModel
from pydantic.json_schema import JsonSchemaMode, models_json_schema

from service.gateway import Gateway, ScanLabeller
from service.http.dependencies import require_token
from service.http.error_handlers import install_error_handlers
from service.http.errors import error_responses
from service.http.metrics import MetricsMiddleware
from service.http.origins import OriginGuard
from service.http.security_headers import NoSniff
from service.jobs import JobExecutor, check_job_database
from service.models.catalog import ModelCatalog
from service.routes.health import router as health_router
from service.routes.jobs import router as jobs_router
from service.routes.model import router as model_router
from service.routes.page import router as page_router
from service.routes.profile import router as profile_router
from service.routes.scans import router as scans_router
from service.schemas import ARCHIVE_UPLOAD, DatasetJobRequest, ErrorResponse, ScanLabels
from service.settings import Settings

#: The groups of operations in the API description (and the modules of a generated client).
TAGS = [
    {"name": "scans", "description": "Label one scan."},
    {"name": "jobs", "description": "Jobs over whole sequences: start, follow, fetch, cancel."},
    {"name": "service", "description": "What the gateway serves, and its health."},
]


#: Bodies the routes describe by hand (they read them themselves), added to the components.
_BODY_MODELS: tuple[tuple[type[BaseModel], JsonSchemaMode], ...] = (
    (DatasetJobRequest, "validation"),
    (ScanLabels, "serialization"),
    (ErrorResponse, "serialization"),
)


def _openapi(app: FastAPI) -> dict[str, Any]:
    """The OpenAPI description: 400 (not FastAPI's 422) for request validation, the bodies the
    routes read themselves among the components, and `/healthz` open to callers without a token."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(
        title=app.title,
        version=app.version,
        description=app.description,
        routes=app.routes,
        tags=TAGS,
    )
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            operation.get("responses", {}).pop("422", None)
    health = schema["paths"]["/healthz"]["get"]
    health["security"] = [{}, *health.get("security", [])]
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components.pop("HTTPValidationError", None)
    components.pop("ValidationError", None)
    _, described = models_json_schema(_BODY_MODELS, ref_template="#/components/schemas/{model}")
    components.update(described.get("$defs", {}))
    components["ArchiveUpload"] = ARCHIVE_UPLOAD
    app.openapi_schema = schema
    return schema


def _served_text(models: ModelCatalog) -> str:
    """What the API description says of the served models and their profiles."""
    parts = [
        f"`{m.name}` (the `{m.profile.name}` profile: {m.profile.points.point_bytes} bytes per point, "
        f"{m.profile.points.describe()})"
        for m in models
    ]
    return (
        f"This gateway serves {'the model ' if len(parts) == 1 else 'the models '}"
        f"{', '.join(parts)}; `{models.default}` is the default. A scan is answered with its "
        "model's raw ids."
    )


def create_app(
    settings: Settings,
    labeller: ScanLabeller,
    executor: JobExecutor,
    *,
    models: ModelCatalog,
) -> FastAPI:
    """The gateway app over a ready labeller of the catalog's models, each of which runs with
    its own profile (point record, labels, layout and splits).

    Refuses (ValueError) a non-loopback host without a token and a job database newer than this code.
    """
    problem = settings.address_problem()
    if problem:
        raise ValueError(problem)
    check_job_database(settings.database_path)
    gateway = Gateway(settings, labeller, executor, models)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await gateway.start()
        try:
            yield
        finally:
            await gateway.stop()

    app = FastAPI(
        title="RangeRet gateway",
        version="1.0",
        description=(
            "LiDAR semantic segmentation with RangeRet over HTTP: label single scans, or run jobs over "
            "whole sequences (uploaded archives or datasets under the data roots) and download the "
            'predictions and the per-class IoU. Errors are `{"detail": "<one sentence>"}`. '
            + _served_text(models)
        ),
        lifespan=lifespan,
        # No trailing-slash redirects: Starlette builds their Location from the request's Host.
        redirect_slashes=False,
        # The API page is the gateway's own (`service.routes.page`), with no file from elsewhere.
        docs_url=None,
        redoc_url=None,
    )
    app.state.gateway = gateway
    app.add_middleware(MetricsMiddleware, metrics=lambda: gateway.metrics)
    app.add_middleware(OriginGuard, allowed_hosts=settings.host_allow_list())
    app.add_middleware(NoSniff)
    install_error_handlers(app)
    # The token guard is on every /v1 route whatever the settings (it lets every request through
    # on a gateway without a token), so the API description, and a client generated from it, is
    # the same for every gateway: the bearer scheme and the 401 answers are always described.
    guarded: dict[str, Any] = {
        "dependencies": [Depends(require_token)],
        "responses": error_responses(401),
    }
    app.include_router(scans_router, **guarded)
    app.include_router(jobs_router, **guarded)
    app.include_router(profile_router, **guarded)
    app.include_router(model_router, **guarded)
    app.include_router(health_router)
    app.include_router(page_router)
    app.openapi = lambda: _openapi(app)
    return app
