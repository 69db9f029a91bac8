"""Who may address the gateway: a `Host` allow-list, and no state-changing request from another
origin.

A gateway without a token would otherwise answer any page a browser runs: a request whose `Host`
is another name (DNS rebinding), or a form another origin posts (`fetch(..., {mode: "no-cors"})`).
`OriginGuard` answers both in JSON before the app sees them:

- a request has one `Host` line: two or more, even equal ones, are a 400 (RFC 9112);
- the `Host` must be one of `allowed_hosts` (400): by default, on a gateway without a token, the
  loopback names and the bound address; set `RANGERET_ALLOWED_HOSTS` to choose them, on any
  gateway. A gateway with a token and no list takes any `Host`: in a cluster, clients send the
  service's name. `/healthz` answers any `Host`, since Kubernetes probes send the pod's IP;
- a request that may change state (not GET, HEAD or OPTIONS) from another origin is 403: judged by
  `Sec-Fetch-Site` where the browser sends it, else by `Origin` against `Host`. A request with
  neither header is no browser's cross-origin request (curl, scripts and generated clients send
  none).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from urllib.parse import urlsplit

from starlette.types import ASGIApp, Receive, Scope, Send

#: The names a loopback gateway answers to.
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
#: Methods that only read.
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
#: Paths any Host may ask for (Kubernetes probes send the pod's IP).
ANY_HOST_PATHS = frozenset({"/healthz"})
#: `Sec-Fetch-Site` values of a request the page itself (or the user) made.
SAME_SITE = frozenset({"same-origin", "none"})


def host_name(value: str) -> str:
    """The name of a `Host` header, lower-case, without its port (IPv6 brackets removed)."""
    text = value.strip().lower()
    if text.startswith("["):
        return text[1:].split("]", 1)[0]
    return text.rsplit(":", 1)[0] if text.count(":") == 1 else text


def default_allowed_hosts(bound: str) -> tuple[str, ...]:
    """The hosts a gateway without a token answers to: the loopback names and its address."""
    return tuple(dict.fromkeys((*LOOPBACK_NAMES, host_name(bound))))


class OriginGuard:
    """ASGI middleware enforcing the Host allow-list (None: any Host) and same-origin writes."""

    def __init__(self, app: ASGIApp, allowed_hosts: Iterable[str] | None) -> None:
        self.app = app
        self.allowed = None if allowed_hosts is None else {host_name(h) for h in allowed_hosts}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        hosts = sum(1 for k, _ in scope["headers"] if k.lower() == b"host")
        if hosts > 1:
            await _refuse(
                send, 400, f"The request has {hosts} Host lines; HTTP/1.1 allows exactly one."
            )
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        path = scope.get("path", "")
        if (
            self.allowed is not None
            and path not in ANY_HOST_PATHS
            and host_name(host) not in self.allowed
        ):
            await _refuse(
                send,
                400,
                f"This gateway does not answer to the host {host[:100]!r}: it answers to "
                f"{', '.join(sorted(self.allowed))} (RANGERET_ALLOWED_HOSTS).",
            )
            return
        if scope.get("method", "GET") not in SAFE_METHODS and _cross_origin(headers, host):
            await _refuse(
                send,
                403,
                "Requests that change state are not taken from another origin's page; send them "
                "from the gateway's own page, or from a client that is not a browser.",
            )
            return
        await self.app(scope, receive, send)


def _cross_origin(headers: dict[str, str], host: str) -> bool:
    """Whether the browser says, or the `Origin` shows, that another origin sent the request."""
    site = headers.get("sec-fetch-site")
    if site is not None:
        return site.strip().lower() not in SAME_SITE
    origin = headers.get("origin")
    if origin is None:
        return False
    parts = urlsplit(origin.strip())
    return not parts.netloc or parts.netloc.lower() != host.strip().lower()


async def _refuse(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})
