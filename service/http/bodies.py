"""Reading request bodies under limits: whole small bodies, and archive uploads streamed to disk.

A body over its limit is answered with 413. So that the client can read that answer instead of
seeing its connection reset mid-upload, a moderately oversized body is read and dropped first;
a body far over the limit (more than `DRAIN_MAX` bytes beyond it) is cut off at once.

Every read has a deadline, `timeout` seconds from when the handler starts reading: a body that
has not all arrived by then is answered with 408 and the connection is closed, and dropping a
body before an error answer stops there too (the error answer then closes the connection).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path
from typing import BinaryIO

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect, Request

from service.http.errors import ApiError
from service.settings import Settings

#: Bytes beyond a limit that are still read (and dropped) so the client sees the 413.
DRAIN_MAX = 64 << 20
#: Bytes a form field other than the archive may hold, and multipart framing allowed over the limit.
_FORM_SLACK = 64 << 10


def media_type(request: Request) -> str:
    """The request's media type, lower case, without parameters ("" when absent)."""
    return request.headers.get("content-type", "").split(";", 1)[0].strip().lower()


def declared_length(request: Request) -> int | None:
    """The Content-Length header as a number, None when absent; 400 when it is not a number."""
    value = request.headers.get("content-length")
    if value is None:
        return None
    try:
        length = int(value)
    except ValueError:
        raise ApiError(400, "The Content-Length header is not a number.") from None
    if length < 0:
        raise ApiError(400, "The Content-Length header is negative.")
    return length


async def refused_body(
    request: Request, settings: Settings, error: ApiError, *, upload: bool = False
) -> ApiError:
    """`error`, to raise once what is left of the body it refuses is dropped (within the
    settings' body limit and the body's, or with `upload` an upload's, time limit)."""
    timeout = settings.upload_timeout_s if upload else settings.body_timeout_s
    await drain(request, settings.max_body_bytes, timeout=timeout)
    return error


async def drain(
    request: Request,
    limit: int = DRAIN_MAX,
    stream: AsyncIterator[bytes] | None = None,
    *,
    timeout: float,
) -> bool:
    """Read and drop what is left of the body (at most `limit` more bytes) before an error answer,
    for at most `timeout` seconds; whether the body has all been read.

    `stream` is the body iterator already being read, when there is one.
    """
    if stream is None:
        length = declared_length(request)
        if length is not None and length > limit:
            return False
        stream = request.stream()
    seen = 0
    try:
        async for chunk in _until(stream, _deadline(timeout)):
            seen += len(chunk)
            if seen > limit:
                return False
    except ClientDisconnect:
        return True
    except TimeoutError:
        return False
    return True


def _deadline(timeout: float) -> float:
    """The event loop's time `timeout` seconds from now."""
    return asyncio.get_running_loop().time() + timeout


def _left(deadline: float) -> float:
    """Seconds left until `deadline` (the event loop's time), never negative."""
    return max(0.0, deadline - asyncio.get_running_loop().time())


async def _until(stream: AsyncIterator[bytes], deadline: float) -> AsyncIterator[bytes]:
    """The chunks of `stream`; TimeoutError when the next one has not come by `deadline`."""
    chunks = aiter(stream)
    while True:
        try:
            chunk = await asyncio.wait_for(anext(chunks), _left(deadline))
        except StopAsyncIteration:
            return
        except asyncio.TimeoutError as exc:  # not yet the built-in TimeoutError on Python 3.10
            raise TimeoutError from exc
        yield chunk


def too_slow(timeout: float, what: str, setting: str) -> ApiError:
    """The 408 answer for a body that did not arrive within `timeout` seconds; it closes the
    connection, whose request is left half read."""
    return ApiError(
        408,
        f"The {what} did not arrive within {timeout:,g} seconds (the limit set by {setting}).",
        {"Connection": "close"},
    )


def _closing(error: ApiError, whole: bool) -> ApiError:
    """`error`, closing the connection when the body it answers has not all been read."""
    if not whole:
        error.headers["Connection"] = "close"
    return error


def too_large(limit: int, what: str = "request body") -> ApiError:
    """The 413 answer for a body over `limit` bytes."""
    return ApiError(413, f"The {what} is larger than the limit of {limit:,} bytes.")


async def read_body(request: Request, limit: int, timeout: float) -> bytes:
    """The whole body, at most `limit` bytes (413 beyond, after draining a moderate excess),
    arrived within `timeout` seconds (408 past them, see RANGERET_BODY_TIMEOUT_S)."""
    deadline = _deadline(timeout)
    length = declared_length(request)
    if length is not None and length > limit:
        whole = await drain(request, limit + DRAIN_MAX, timeout=timeout)
        raise _closing(too_large(limit), whole)
    body = bytearray()
    stream = _until(request.stream(), deadline)
    try:
        async for chunk in stream:
            body += chunk
            if len(body) > limit:
                whole = await drain(request, DRAIN_MAX, stream, timeout=_left(deadline))
                raise _closing(too_large(limit), whole)
    except TimeoutError:
        raise too_slow(timeout, "request body", "RANGERET_BODY_TIMEOUT_S") from None
    return bytes(body)


class _ArchivePart:
    """Multipart callbacks that route the `archive` field's bytes to a file, in order."""

    def __init__(self) -> None:
        self.headers: dict[bytes, bytes] = {}
        self._field = b""
        self._value = b""
        self.current: bytes | None = None
        self.seen_archive = False
        self.other_bytes = 0
        self.pending: list[bytes] = []
        self.other_field: str | None = None

    def callbacks(self) -> dict:
        return {
            "on_part_begin": self.on_part_begin,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
            "on_part_data": self.on_part_data,
        }

    def on_part_begin(self) -> None:
        self.headers = {}
        self.current = None

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._field += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]

    def on_header_end(self) -> None:
        self.headers[self._field.lower()] = self._value
        self._field = self._value = b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self.headers.get(b"content-disposition", b""))
        self.current = options.get(b"name", b"")
        if self.current == b"archive":
            if self.seen_archive:
                raise ApiError(400, "The form holds more than one 'archive' field.")
            self.seen_archive = True
        elif self.other_field is None:
            self.other_field = self.current.decode("latin-1")[:100]

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self.current == b"archive":
            self.pending.append(data[start:end])
        else:
            self.other_bytes += end - start


async def receive_archive(request: Request, target: Path, limit: int, timeout: float) -> int:
    """Stream the multipart field `archive` into `target`; its size in bytes.

    400 for a malformed form, one without an `archive` file or with any other field, 413 over
    `limit` bytes, 408 when
    the body has not all arrived within `timeout` seconds (RANGERET_UPLOAD_TIMEOUT_S).
    """
    deadline = _deadline(timeout)
    _, options = parse_options_header(request.headers.get("content-type", ""))
    boundary = options.get(b"boundary")
    if not boundary:
        whole = await drain(request, timeout=timeout)
        raise _closing(
            ApiError(400, "The multipart/form-data body has no boundary parameter."), whole
        )
    length = declared_length(request)
    if length is not None and length > limit + _FORM_SLACK:
        whole = await drain(request, limit + DRAIN_MAX, timeout=timeout)
        raise _closing(too_large(limit, "archive"), whole)
    part = _ArchivePart()
    parser = MultipartParser(boundary, part.callbacks())
    size = 0
    stream = _until(request.stream(), deadline)

    async def refuse(error: ApiError) -> ApiError:
        whole = await drain(request, DRAIN_MAX, stream, timeout=_left(deadline))
        return _closing(error, whole)

    with open(target, "wb") as out:
        try:
            async for chunk in stream:
                parser.write(chunk)
                if part.other_bytes > _FORM_SLACK:
                    raise await refuse(
                        ApiError(
                            400,
                            f"The form field {part.other_field!r} is unexpected: "
                            "send only 'archive'.",
                        )
                    )
                if part.pending:
                    data = b"".join(part.pending)
                    part.pending.clear()
                    size += len(data)
                    if size > limit:
                        raise await refuse(too_large(limit, "archive"))
                    await asyncio.to_thread(_write, out, data)
            parser.finalize()
        except FormParserError as exc:
            error = ApiError(400, f"The multipart/form-data body is malformed ({exc}).")
            raise await refuse(error) from exc
        except TimeoutError:
            raise too_slow(timeout, "archive upload", "RANGERET_UPLOAD_TIMEOUT_S") from None
    if not part.seen_archive:
        raise ApiError(400, "The form has no 'archive' file field (a .zip, .tar or .tar.gz).")
    if part.other_field is not None:
        raise ApiError(
            400, f"The form field {part.other_field!r} is unexpected: send only 'archive'."
        )
    return size


def _write(out: BinaryIO, data: bytes) -> None:
    out.write(data)
