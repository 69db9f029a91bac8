"""The gateway's error answers: `{"detail": "<one readable sentence>"}` with the status code."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from service.schemas import ErrorResponse

#: Sentences for the status codes Starlette raises by itself with its short phrases.
_DEFAULT_SENTENCES = {
    404: "There is no such endpoint or resource.",
    405: "This endpoint does not accept that HTTP method.",
}

_KINDS = {
    "setting": "setting",
    "query": "query parameter",
    "path": "path parameter",
    "header": "header",
    "cookie": "cookie",
    "body": "body field",
}

_DESCRIPTIONS = {
    400: "Malformed request, or a Host the gateway does not answer to (RANGERET_ALLOWED_HOSTS)",
    401: "Missing or wrong bearer token, where the gateway has one (RANGERET_API_TOKEN)",
    403: "A state-changing request from another origin's page",
    404: "No such job or result",
    408: "The body did not arrive in time (RANGERET_BODY_TIMEOUT_S, RANGERET_UPLOAD_TIMEOUT_S)",
    409: "The job has not succeeded (yet)",
    413: "Body, scan or archive over the configured limits",
    415: "Wrong media type",
    429: "Too many jobs are waiting (RANGERET_MAX_QUEUED_JOBS)",
    503: "The gateway is starting",
    504: "The Serve application did not answer in time (RANGERET_SERVE_TIMEOUT_S)",
    507: "No room: the job folders' limit (RANGERET_MAX_JOB_BYTES) or disk, or a full disk under the job database",
}


class ApiError(Exception):
    """An error to answer with `status_code` and a one-sentence `detail`."""

    def __init__(
        self, status_code: int, detail: str, headers: Mapping[str, str] | None = None
    ) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = sentence(detail)
        self.headers = dict(headers or {})


def sentence(text: str) -> str:
    """`text` as one sentence: single spaces, capitalised, ending with a full stop."""
    text = " ".join(str(text).split())
    if not text:
        return "The request failed."
    text = text[0].upper() + text[1:]
    return text if text.endswith((".", "!", "?")) else text + "."


def default_sentence(status_code: int, detail: Any) -> str:
    """Starlette's short phrases ("Not Found") as sentences; other details kept."""
    if (
        isinstance(detail, str)
        and detail
        and " " in detail.strip()
        and status_code not in _DEFAULT_SENTENCES
    ):
        return sentence(detail)
    return _DEFAULT_SENTENCES.get(status_code, sentence(str(detail or "The request failed")))


def validation_sentence(errors: Sequence[Mapping[str, Any]], where: str | None = None) -> str:
    """One sentence for pydantic/FastAPI validation errors: the first problem, and how many more."""
    if not errors:
        return "The request is invalid."
    first = errors[0]
    loc = [str(p) for p in first.get("loc", ())]
    if loc and loc[0] in _KINDS and where is None:
        where, loc = loc[0], loc[1:]
    message = str(first.get("msg", "is invalid")).removeprefix("Value error, ").rstrip(".")
    more = f" (and {len(errors) - 1} more problem(s))" if len(errors) > 1 else ""
    if loc:
        kind = _KINDS.get(where or "body", "field")
        return sentence(f"The {kind} '{'.'.join(loc)}' is invalid: {message}{more}")
    if where == "body":
        return sentence(f"The request body is invalid: {message}{more}")
    return sentence(f"The request is invalid: {message}{more}")


def error_responses(
    *codes: int, described: Mapping[int, str] | None = None
) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for error codes, all with the `ErrorResponse` body; `described`
    gives a route's own description of some of them."""
    described = described or {}
    return {
        code: {"model": ErrorResponse, "description": described.get(code, _DESCRIPTIONS[code])}
        for code in codes
    }
