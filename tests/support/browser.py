"""A real browser for the web page's tests: Debian's chromium driven by Playwright, a page that
records its console errors and failed requests, and a reverse proxy that serves the gateway under
a path prefix as nginx's `location /rangeret/ { proxy_pass http://gateway/; }` does."""

from __future__ import annotations

import http.client
import shutil
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlsplit

import pytest

#: What `make test` installs the browser with, for the message when it is missing.
INSTALL = "apt-get install -y --no-install-recommends chromium (or run make test as root)"
#: Software WebGL in a headless browser without a GPU.
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def chromium_path() -> str:
    """The chromium executable on PATH; the test fails naming the install command without it."""
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.fail(f"The browser tests need chromium on PATH: {INSTALL}.")
    return path


@dataclass
class PageLog:
    """What went wrong while a page was open: console errors, uncaught errors, failed requests."""

    errors: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)

    def watch(self, page) -> None:
        page.on(
            "console",
            lambda msg: self.errors.append(f"console: {msg.text}") if msg.type == "error" else None,
        )
        page.on("pageerror", lambda exc: self.errors.append(f"page: {exc}"))
        page.on(
            "response",
            lambda r: self.failed.append(f"{r.status} {r.url}") if r.status >= 400 else None,
        )
        page.on("requestfailed", lambda r: self.failed.append(f"failed {r.url}"))


# A reverse proxy under a path prefix -------------------------------------------------------------

_HOP_BY_HOP = {
    "connection",
    "keep-alive",
    "proxy-authenticate",
    "proxy-authorization",
    "te",
    "trailers",
    "transfer-encoding",
    "upgrade",
    "host",
}


class _PrefixHandler(BaseHTTPRequestHandler):
    """Forwards `/PREFIX/rest` to the upstream's `/rest`; anything else is 404."""

    protocol_version = "HTTP/1.1"
    server: _PrefixServer

    def log_message(self, format: str, *args: object) -> None:  # quiet
        return

    def _forward(self) -> None:
        prefix = self.server.prefix
        if not self.path.startswith(prefix + "/"):
            self.send_response(404)
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        length = int(self.headers.get("Content-Length") or 0)
        body = self.rfile.read(length) if length else None
        headers = {k: v for k, v in self.headers.items() if k.lower() not in _HOP_BY_HOP}
        upstream = http.client.HTTPConnection(*self.server.upstream, timeout=300)
        try:
            upstream.request(self.command, self.path[len(prefix) :], body=body, headers=headers)
            answer = upstream.getresponse()
            data = answer.read()
            self.send_response(answer.status)
            for key, value in answer.getheaders():
                if key.lower() not in _HOP_BY_HOP and key.lower() != "content-length":
                    self.send_header(key, value)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
        finally:
            upstream.close()

    do_GET = do_POST = do_DELETE = do_HEAD = _forward


class _PrefixServer(ThreadingHTTPServer):
    daemon_threads = True
    prefix: str
    upstream: tuple[str, int]

    def handle_error(self, request: object, client_address: object) -> None:
        """A browser that drops a connection it no longer needs is no error of the proxy."""
        return


@contextmanager
def prefix_proxy(upstream_url: str, prefix: str) -> Iterator[str]:
    """A proxy on a free loopback port serving `upstream_url` under `prefix`; yields its base URL."""
    target = urlsplit(upstream_url)
    server = _PrefixServer(("127.0.0.1", 0), _PrefixHandler)
    server.prefix = prefix.rstrip("/")
    server.upstream = (target.hostname, target.port)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}{server.prefix}/"
    finally:
        server.shutdown()
        server.server_close()
