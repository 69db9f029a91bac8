"""Uvicorn's HTTP/1.1 protocol with the gateway's error format for answers the app never sees.

uvicorn answers by itself, in `text/plain`, a request its parser rejects ("Invalid HTTP request
received.") and a request over `limit_concurrency`. The protocol classes here answer both as
`{"detail": "<one sentence>"}` with `Content-Type: application/json` and `Connection: close`:

- 400 for a request that is not valid HTTP (a Content-Length that is not a number, two different
  Content-Length headers, Transfer-Encoding with Content-Length, a garbage request line, ...),
  naming the parser's reason; with h11, 431 for a request head over its incomplete-event size.
- 503 for a request on a connection beyond the limit (`RANGERET_MAX_CONNECTIONS`): at most that
  many connections are served at once.

A request line and headers must arrive within `header_timeout` seconds of the connection opening
or of the previous answer (`RANGERET_HEADER_TIMEOUT_S`): past it a partly sent head is answered
with a JSON 408 and a connection that sent nothing is closed, so idle or trickling connections
cannot take every place under the connection limit; a head over `MAX_HEAD_BYTES` is answered with
a JSON 431.

An answer sent before its request's body has all arrived (an early error, a body dropped after
its deadline) leaves the rest of the body to be read and dropped; the connection is closed
`LEFTOVER_BODY_S` seconds after that answer unless a further request has started on it, so a
client that declared more bytes than it sends cannot hold the connection.

A request whose target is in absolute form (`GET http://host/path`) is addressed to the target's
authority, whatever its Host lines say (RFC 9112): the protocol puts that authority in their place,
so the Host allow-list judges it.

`GatewayProtocol` mirrors uvicorn's `auto` choice: httptools when it is importable, else h11.
"""

from __future__ import annotations

import asyncio
import http
import json
import logging
import re
import sys
from collections.abc import Sequence
from typing import Any

import h11
from uvicorn._types import ASGIReceiveCallable, ASGISendCallable, Scope
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.http.errors import sentence

log = logging.getLogger("uvicorn.error")

#: Seconds a connection stays open after an answer sent before its request body had all arrived.
LEFTOVER_BODY_S = 30.0
#: Default seconds a request line and headers may take to arrive (RANGERET_HEADER_TIMEOUT_S).
HEADER_TIMEOUT_S = 10.0
#: Largest request line and headers accepted: httptools is stopped while it parses a larger one,
#: h11 refuses a head spread over reads beyond 16 KiB by itself, and the app never sees one.
MAX_HEAD_BYTES = 64 << 10
#: Longest parser reason quoted in a 400 answer.
_REASON_MAX = 80
_UNSAFE = re.compile(r"[^ -~]+")
#: The request bytes h11 quotes after its reason ("illegal header line: b'...'").
_QUOTED = re.compile(r":\s*b?['\"].*$")


def parser_reason(exc: BaseException | None) -> str:
    """The parser's reason for rejecting a request, short and safe to quote: printable ASCII,
    without the request bytes some messages append after a colon, at most `_REASON_MAX` chars."""
    if exc is None:
        return ""
    text = _QUOTED.sub("", _UNSAFE.sub(" ", str(exc)))
    text = " ".join(text.split()).rstrip(".")
    if len(text) > _REASON_MAX:
        text = text[: _REASON_MAX - 3].rstrip() + "..."
    return text


class HeadTooLarge(Exception):
    """A request line and headers over `MAX_HEAD_BYTES` (raised inside the parser's callbacks)."""

    error_status_hint = 431


def invalid_request_answer(exc: BaseException | None) -> tuple[int, str]:
    """The status and sentence answering a request the parser rejected with `exc` (or with an
    error raised in one of its callbacks, which the parser wraps)."""
    causes = [exc, getattr(exc, "__cause__", None), getattr(exc, "__context__", None)]
    status = max((getattr(c, "error_status_hint", 400) for c in causes if c), default=400)
    if status == 431:
        return 431, "The request line and headers are larger than the gateway accepts."
    reason = parser_reason(exc)
    if reason:
        return 400, sentence(f"The request is not valid HTTP ({reason})")
    return 400, "The request is not valid HTTP."


def absolute_form_authority(target: bytes) -> bytes | None:
    """The authority (host and port) of an absolute-form request target (`http://host/path`),
    which RFC 9112 makes the request's host in place of its Host lines; None for another form."""
    scheme, sep, rest = target.partition(b"://")
    if not sep or scheme.lower() not in (b"http", b"https"):
        return None
    authority = rest.split(b"/", 1)[0].split(b"?", 1)[0]
    return authority.rpartition(b"@")[2]


def head_size(scope: Scope) -> int:
    """The bytes of a request's target and headers, as they came."""
    target = len(scope.get("raw_path") or b"") + len(scope.get("query_string") or b"")
    return target + sum(len(name) + len(value) + 4 for name, value in scope.get("headers", ()))


def error_body(detail: str) -> bytes:
    """The JSON error body for `detail`, as the app's error answers write it."""
    return json.dumps({"detail": detail}, ensure_ascii=False, separators=(",", ":")).encode()


def error_response_bytes(
    status: int, detail: str, default_headers: Sequence[tuple[bytes, bytes]] = ()
) -> bytes:
    """A whole HTTP/1.1 error answer that closes the connection, as bytes to write."""
    body = error_body(detail)
    phrase = http.HTTPStatus(status).phrase
    lines = [f"HTTP/1.1 {status} {phrase}\r\n".encode()]
    lines += [name + b": " + value + b"\r\n" for name, value in default_headers]
    lines += [
        b"content-type: application/json\r\n",
        b"content-length: %d\r\n" % len(body),
        b"connection: close\r\n",
        b"\r\n",
        body,
    ]
    return b"".join(lines)


async def send_error(send: ASGISendCallable, status: int, detail: str) -> None:
    """Answer an ASGI request with the JSON error and `Connection: close`."""
    body = error_body(detail)
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body, "more_body": False})


class _GatewayAnswers:
    """What both protocol classes add to uvicorn's: JSON for the 400 and the 503, the connection
    limit checked when the request reaches the app, and a bound on a body left unread.

    A mixin placed before uvicorn's protocol class; it relies on that class's attributes."""

    #: Seconds a request head may take to arrive; set per server by `with_header_timeout`.
    header_timeout: float = HEADER_TIMEOUT_S

    app: Any
    limit_concurrency: int | None
    connections: set[Any]
    tasks: set[asyncio.Task[None]]
    transport: asyncio.Transport
    loop: asyncio.AbstractEventLoop
    server_state: Any
    cycle: Any

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # uvicorn would answer a request over its limit with its own text/plain 503: keep the
        # limit here instead and check it in `_admit`, which answers in JSON.
        self.connection_limit = self.limit_concurrency
        self.limit_concurrency = None
        self._inner_app = self.app
        self.app = self._admit
        self._leftover_timer: asyncio.TimerHandle | None = None
        self._head_timer: asyncio.TimerHandle | None = None
        self._head_bytes = 0
        self._head_cycle: Any = None

    @classmethod
    def with_header_timeout(cls, seconds: float) -> type[asyncio.Protocol]:
        """This protocol with request heads bounded to `seconds` (RANGERET_HEADER_TIMEOUT_S)."""
        return type(cls.__name__, (cls,), {"header_timeout": seconds})

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        """uvicorn's, and the wait for the first request's head started."""
        super().connection_made(transport)  # type: ignore[misc]
        self._start_head_timer()

    def data_received(self, data: bytes) -> None:
        """uvicorn's, noting whether part of an awaited request head has come."""
        if self._awaiting_head():
            self._head_bytes += len(data)
        super().data_received(data)  # type: ignore[misc]

    def _awaiting_head(self) -> bool:
        """Whether the connection waits for a request head: the timer runs and no request has
        been parsed since it started (each parsed head makes a new `cycle`)."""
        return self._head_timer is not None and self.cycle is self._head_cycle

    def _start_head_timer(self) -> None:
        self._cancel_head_timer()
        self._head_bytes = 0
        self._head_cycle = self.cycle
        self._head_timer = self.loop.call_later(self.header_timeout, self._head_overdue)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_overdue(self) -> None:
        """No whole request head came in time: a JSON 408 when part of one came, then close."""
        if not self._awaiting_head() or self.transport.is_closing():
            self._head_timer = None
            return
        self._head_timer = None
        if self._head_bytes:
            log.info("a request head did not arrive within %g s; answered 408", self.header_timeout)
            detail = (
                f"The request line and headers did not arrive within {self.header_timeout:,g} "
                "seconds (the limit set by RANGERET_HEADER_TIMEOUT_S)."
            )
            self.transport.write(
                error_response_bytes(408, detail, self.server_state.default_headers)
            )
        self.transport.close()

    def _body_pending(self) -> bool:
        """Whether the current request's body has not all arrived yet."""
        raise NotImplementedError

    def _over_limit(self) -> bool:
        """Whether this request's connection (counted in `connections`) or its task (in `tasks`)
        is beyond the connection limit."""
        limit = self.connection_limit
        return limit is not None and (len(self.connections) > limit or len(self.tasks) > limit)

    async def _admit(
        self, scope: Scope, receive: ASGIReceiveCallable, send: ASGISendCallable
    ) -> None:
        """The app, or a JSON 503 for a request beyond the connection limit."""
        self._cancel_head_timer()
        if scope["type"] == "http" and head_size(scope) > MAX_HEAD_BYTES:
            await send_error(
                send, 431, "The request line and headers are larger than the gateway accepts."
            )
            return
        if scope["type"] == "http" and self._over_limit():
            log.warning("over the limit of %d connections; answered 503", self.connection_limit)
            await send_error(
                send,
                503,
                f"The gateway is serving its limit of {self.connection_limit:,} connections "
                "(RANGERET_MAX_CONNECTIONS); try again later.",
            )
            return
        await self._inner_app(scope, receive, send)

    def send_400_response(self, msg: str) -> None:
        """Answer a request the parser rejected, in JSON, and close the connection.

        uvicorn calls this inside its `except` for the parser's error, so that error is the one
        being handled. When an answer is already being written, a second one would corrupt it:
        the connection is only closed."""
        exc = sys.exc_info()[1]
        cycle = self.cycle
        if cycle is not None and not cycle.response_complete:
            writing = cycle.response_started
            cycle.disconnected = True  # the app's answer, if any, is no longer written
            cycle.message_event.set()
            if writing:
                self.transport.close()
                return
        status, detail = invalid_request_answer(exc)
        log.debug("invalid HTTP request (%s); answered %d", parser_reason(exc) or msg, status)
        self.transport.write(
            error_response_bytes(status, detail, self.server_state.default_headers)
        )
        self.transport.close()

    def on_response_complete(self) -> None:
        """uvicorn's bookkeeping; then, when the request's body is still arriving, a timer that
        closes the connection unless a further request starts on it in time."""
        super().on_response_complete()  # type: ignore[misc]
        if self.transport.is_closing():
            return
        if not self._body_pending():
            self._start_head_timer()
            return
        self._cancel_leftover_timer()
        self._leftover_timer = self.loop.call_later(
            LEFTOVER_BODY_S, self._close_if_idle, self.cycle
        )

    def _close_if_idle(self, cycle: Any) -> None:
        """Close the connection unless a request after `cycle` has reached the app."""
        self._leftover_timer = None
        if self.cycle is cycle and not self.transport.is_closing():
            self.transport.close()

    def _cancel_leftover_timer(self) -> None:
        if self._leftover_timer is not None:
            self._leftover_timer.cancel()
            self._leftover_timer = None

    def connection_lost(self, exc: Exception | None) -> None:
        """uvicorn's, and the timers cancelled."""
        self._cancel_leftover_timer()
        self._cancel_head_timer()
        super().connection_lost(exc)  # type: ignore[misc]


class JsonH11Protocol(_GatewayAnswers, H11Protocol):
    """uvicorn's h11 protocol with the gateway's JSON answers."""

    conn: h11.Connection

    def _body_pending(self) -> bool:
        return self.conn.their_state is h11.SEND_BODY


GatewayProtocol: type[asyncio.Protocol]

try:
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:  # no httptools: uvicorn's `auto` would run h11
    GatewayProtocol = JsonH11Protocol
else:

    class JsonHttpToolsProtocol(_GatewayAnswers, HttpToolsProtocol):
        """uvicorn's httptools protocol with the gateway's JSON answers."""

        _message_done = True
        _parsed_head = 0

        def on_message_begin(self) -> None:
            self._message_done = False
            self._parsed_head = 0
            super().on_message_begin()

        def on_url(self, url: bytes) -> None:
            self._count_head(len(url))
            super().on_url(url)

        def on_header(self, name: bytes, value: bytes) -> None:
            self._count_head(len(name) + len(value) + 4)
            super().on_header(name, value)

        def _count_head(self, size: int) -> None:
            """httptools bounds no head: refuse one over `MAX_HEAD_BYTES` with a 431."""
            self._parsed_head += size
            if self._parsed_head > MAX_HEAD_BYTES:
                raise HeadTooLarge

        def on_headers_complete(self) -> None:
            authority = absolute_form_authority(self.url)
            if authority is not None:  # RFC 9112 3.2.2: the target's authority is the host
                hosts = [i for i, (name, _) in enumerate(self.headers) if name == b"host"]
                for i in hosts:
                    self.headers[i] = (b"host", authority)
                if not hosts:
                    self.headers.append((b"host", authority))
            super().on_headers_complete()

        def on_message_complete(self) -> None:
            # uvicorn ignores the end of a body whose answer is already sent; note it here.
            self._message_done = True
            super().on_message_complete()

        def _body_pending(self) -> bool:
            return not self._message_done

    GatewayProtocol = JsonHttpToolsProtocol
