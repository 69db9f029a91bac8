"""The app's exception handlers: every error is answered as `{"detail": "<one sentence>"}`.

`ApiError` keeps its status, sentence and headers; Starlette's own errors (404, 405) get readable
sentences; request validation errors become 400 (not FastAPI's 422); a full disk (the job
database's, or where an upload is written) is 507 naming it; anything else is a logged 500.
"""

from __future__ import annotations

import errno
import logging
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from service.http.errors import ApiError, default_sentence, sentence, validation_sentence
from service.jobs import JobDatabaseFull
from service.schemas import ErrorResponse

log = logging.getLogger(__name__)


def error_response(
    status_code: int, detail: str, headers: dict[str, str] | None = None
) -> JSONResponse:
    """The JSON error answer: `ErrorResponse` with the status code and headers."""
    return JSONResponse(
        ErrorResponse(detail=detail).model_dump(), status_code=status_code, headers=headers
    )


async def api_error(_: Request, exc: ApiError) -> JSONResponse:
    """An error the gateway raised on purpose, as it is."""
    return error_response(exc.status_code, exc.detail, exc.headers)


#: The methods a 405's `Allow` may list, probed in this order.
_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(request: Request) -> list[str]:
    """Every method some route of the app accepts at the request's path, for a 405's `Allow`.

    Each method is tried against the app's routes, so routes of included routers count too.
    """
    routes = request.app.router.routes
    return [
        method
        for method in _METHODS
        if any(
            route.matches({**request.scope, "method": method})[0] is Match.FULL for route in routes
        )
    ]


async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    """Starlette's HTTP errors, with its short phrases turned into sentences; a 405 lists every
    method of the path in `Allow`, not only that of the first route that matched it."""
    headers = dict(getattr(exc, "headers", None) or {})
    detail = default_sentence(exc.status_code, exc.detail)
    if exc.status_code == 405:
        allowed = allowed_methods(request)
        if allowed:
            headers["Allow"] = ", ".join(allowed)
            detail = f"This endpoint accepts {', '.join(allowed)}, not {request.method[:20]}."
    return error_response(exc.status_code, detail, headers or None)


async def invalid_request(_: Request, exc: RequestValidationError) -> JSONResponse:
    """A query, path or body that does not validate: 400 with the first problem."""
    return error_response(400, validation_sentence(exc.errors()))


async def database_full(_: Request, exc: JobDatabaseFull) -> JSONResponse:
    """The job database's disk is full: 507 naming it."""
    log.warning("%s", exc)
    return error_response(507, sentence(f"Insufficient storage: {exc}"))


async def unexpected(_: Request, exc: Exception) -> JSONResponse:
    """Any other exception: logged with its traceback, answered with a 500 sentence; a disk
    that is full (ENOSPC, EDQUOT) is a 507 naming the folder instead."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        where = Path(str(exc.filename)).parent if exc.filename else "the gateway's state folder"
        log.warning("no space left on the disk of %s: %s", where, exc)
        return error_response(
            507, sentence(f"Insufficient storage: the disk of {where} is full; free space there")
        )
    log.error("unexpected error", exc_info=exc)
    return error_response(500, "The gateway failed unexpectedly; the error is in its log.")


def install_error_handlers(app: FastAPI) -> None:
    """Answer every error of `app` in the JSON error format."""
    app.add_exception_handler(ApiError, api_error)
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(RequestValidationError, invalid_request)
    app.add_exception_handler(JobDatabaseFull, database_full)
    app.add_exception_handler(Exception, unexpected)
