"""What the gateway answers below the app: requests its HTTP parser rejects, bodies that do not
arrive in time, connections beyond its limit.

Raw sockets send what an HTTP client would refuse to; every answer must be the gateway's JSON
error and close the connection. A socket timeout well above the deadlines turns a connection the
gateway holds open into a failure.
"""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import uvicorn
from starlette.requests import Request

import service.http.protocols as protocols
from service.http.bodies import drain, read_body, receive_archive
from service.http.errors import ApiError
from service.http.protocols import GatewayProtocol, JsonH11Protocol
from tests.support.gateway import TOKEN, Gateway, free_port, gateway_env, start_gateway
from tests.support.workers import small_weights

#: Seconds a test waits for an answer: far beyond every deadline of these gateways.
SOCKET_TIMEOUT = 30
BODY_TIMEOUT_S = 2
UPLOAD_TIMEOUT_S = 3
MAX_CONNECTIONS = 3
#: The request-head deadline of the small servers.
HEADER_TIMEOUT_S = 3


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    body: bytes
    closed: bool


def exchange(port: int, data: bytes, timeout: float = SOCKET_TIMEOUT) -> Answer:
    """Send `data` on a new connection and read until the gateway closes it."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(data)
        return read_answer(sock)


def read_answer(sock: socket.socket) -> Answer:
    """Read one answer and what follows it until the peer closes the connection; a reset after
    the answer counts as closed. Fails when nothing closes it within the socket's timeout."""
    raw = b""
    closed = False
    while True:
        try:
            chunk = sock.recv(65536)
        except TimeoutError:
            pytest.fail(f"no answer, or the connection stayed open; read so far: {raw[:300]!r}")
        except ConnectionResetError:
            closed = True
            break
        if not chunk:
            closed = True
            break
        raw += chunk
    head, sep, body = raw.partition(b"\r\n\r\n")
    assert sep, f"no complete answer: {raw[:300]!r}"
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {}
    for line in lines[1:]:
        name, _, value = line.partition(":")
        headers[name.strip().lower()] = value.strip()
    return Answer(status, headers, body, closed)


def assert_json_error(answer: Answer, status: int) -> str:
    """The answer is the gateway's JSON error with `status`, whole, and closes the connection."""
    assert answer.status == status, answer
    assert answer.headers["content-type"].startswith("application/json"), answer.headers
    assert int(answer.headers["content-length"]) == len(answer.body), answer
    assert answer.headers.get("connection", "").lower() == "close", answer.headers
    assert answer.closed
    body = json.loads(answer.body)
    assert set(body) == {"detail"} and isinstance(body["detail"], str)
    detail = body["detail"]
    assert detail.endswith(".") and "\n" not in detail and detail[0].isupper()
    assert detail.count(". ") == 0, detail
    return detail


def port_of(gw: Gateway) -> int:
    return int(gw.url.rsplit(":", 1)[1])


# Gateways ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return small_weights(tmp_path_factory.mktemp("weights"))


@pytest.fixture(scope="module")
def gateway(tmp_path_factory, weights) -> Iterator[Gateway]:
    """A gateway with short body deadlines."""
    base = tmp_path_factory.mktemp("protocol")
    (base / "roots").mkdir()
    env = gateway_env(
        base / "state",
        [base / "roots"],
        RANGERET_BODY_TIMEOUT_S=str(BODY_TIMEOUT_S),
        RANGERET_UPLOAD_TIMEOUT_S=str(UPLOAD_TIMEOUT_S),
    )
    gw = start_gateway(weights, env, base / "gateway.log")
    yield gw
    gw.stop()


@pytest.fixture(scope="module")
def limited(tmp_path_factory, weights) -> Iterator[Gateway]:
    """A gateway that serves at most `MAX_CONNECTIONS` connections."""
    base = tmp_path_factory.mktemp("limited")
    (base / "roots").mkdir()
    env = gateway_env(
        base / "state", [base / "roots"], RANGERET_MAX_CONNECTIONS=str(MAX_CONNECTIONS)
    )
    gw = start_gateway(weights, env, base / "gateway.log")
    yield gw
    gw.stop()


# Requests the parser rejects -------------------------------------------------------------------

AUTH_LINE = f"Authorization: Bearer {TOKEN}\r\n".encode()
INVALID = {
    "length-not-a-number": b"POST /v1/scans HTTP/1.1\r\nHost: t\r\nContent-Length: 12abc\r\n\r\n",
    "two-lengths": (
        b"POST /v1/scans HTTP/1.1\r\nHost: t\r\nContent-Length: 4\r\nContent-Length: 8\r\n\r\nabcd"
    ),
    "chunked-and-length": (
        b"POST /v1/scans HTTP/1.1\r\nHost: t\r\nTransfer-Encoding: chunked\r\n"
        b"Content-Length: 5\r\n\r\n5\r\nhello\r\n0\r\n\r\n"
    ),
    "garbage-request-line": b"\x16\x03\x01 HELLO THERE\r\n\r\n",
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_http_is_answered_in_json(gateway, case):
    detail = assert_json_error(exchange(port_of(gateway), INVALID[case]), 400)
    assert detail.startswith("The request is not valid HTTP"), detail
    assert len(detail) < 160


def test_gateway_still_answers_after_invalid_requests(gateway):
    with gateway.client() as client:
        assert client.get("/healthz").status_code == 200


# Bodies that do not arrive -----------------------------------------------------------------------


def test_scan_body_slower_than_its_deadline_is_408(gateway):
    head = (
        b"POST /v1/scans HTTP/1.1\r\nHost: t\r\n" + AUTH_LINE + b"Content-Type: "
        b"application/octet-stream\r\nContent-Length: 160000\r\n\r\n"
    )
    detail = assert_json_error(exchange(port_of(gateway), head + b"\0" * 1600), 408)
    assert "RANGERET_BODY_TIMEOUT_S" in detail and f"{BODY_TIMEOUT_S} seconds" in detail


def test_json_job_body_slower_than_its_deadline_is_408(gateway):
    head = (
        b"POST /v1/jobs HTTP/1.1\r\nHost: t\r\n" + AUTH_LINE + b"Content-Type: "
        b"application/json\r\nContent-Length: 500\r\n\r\n"
    )
    detail = assert_json_error(exchange(port_of(gateway), head + b'{"dataset": '), 408)
    assert "RANGERET_BODY_TIMEOUT_S" in detail


def test_archive_upload_slower_than_its_deadline_is_408(gateway):
    part = (
        b'--xyz\r\nContent-Disposition: form-data; name="archive"; filename="a.zip"\r\n'
        b"Content-Type: application/zip\r\n\r\nPK\x03\x04" + b"\0" * 4000
    )
    head = (
        b"POST /v1/jobs HTTP/1.1\r\nHost: t\r\n" + AUTH_LINE + b"Content-Type: "
        b"multipart/form-data; boundary=xyz\r\nContent-Length: 1000000\r\n\r\n"
    )
    detail = assert_json_error(exchange(port_of(gateway), head + part), 408)
    assert "RANGERET_UPLOAD_TIMEOUT_S" in detail and f"{UPLOAD_TIMEOUT_S} seconds" in detail
    with gateway.client() as client:
        assert client.get("/v1/jobs").json()["jobs"] == []


# Connections beyond the limit ------------------------------------------------------------------


def test_connections_beyond_the_limit_get_json_503(limited):
    port = port_of(limited)
    held = [socket.create_connection(("127.0.0.1", port)) for _ in range(MAX_CONNECTIONS)]
    try:
        time.sleep(0.5)  # the gateway has accepted them
        request = b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n"
        detail = assert_json_error(exchange(port, request), 503)
        assert "RANGERET_MAX_CONNECTIONS" in detail and f"{MAX_CONNECTIONS}" in detail
    finally:
        for sock in held:
            sock.close()
    deadline = time.time() + 10
    while time.time() < deadline:
        answer = exchange(port, b"GET /healthz HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n")
        if answer.status == 200:
            return
        time.sleep(0.2)
    pytest.fail(f"the gateway still refuses connections once the others closed: {answer}")


def test_connections_within_the_limit_are_served(limited):
    port = port_of(limited)
    held = [socket.create_connection(("127.0.0.1", port)) for _ in range(MAX_CONNECTIONS - 1)]
    try:
        time.sleep(0.5)
        request = b"GET /healthz HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n"
        assert exchange(port, request).status == 200
    finally:
        for sock in held:
            sock.close()


# Both of uvicorn's protocols, with a small app ---------------------------------------------------


async def small_app(scope, receive, send) -> None:
    """Answers 200 at once, without reading the body."""
    if scope["type"] != "http":
        return
    await send(
        {"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"2")]}
    )
    await send({"type": "http.response.body", "body": b"ok"})


@pytest.fixture(params=[GatewayProtocol, JsonH11Protocol], ids=lambda cls: cls.__name__)
def small_server(request, monkeypatch) -> Iterator[int]:
    """uvicorn in a thread with one of the gateway's protocol classes, a limit of 2 connections
    and a short wait for a body left unread; its port."""
    monkeypatch.setattr(protocols, "LEFTOVER_BODY_S", 0.5)
    port = free_port()
    config = uvicorn.Config(
        small_app,
        host="127.0.0.1",
        port=port,
        http=request.param.with_header_timeout(HEADER_TIMEOUT_S),
        limit_concurrency=2,
        log_level="error",
        lifespan="off",
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.time() + 10
    while not server.started and time.time() < deadline:
        time.sleep(0.02)
    assert server.started
    yield port
    server.should_exit = True
    thread.join(10)


def test_protocols_answer_invalid_http_in_json(small_server):
    detail = assert_json_error(exchange(small_server, INVALID["two-lengths"]), 400)
    assert detail.startswith("The request is not valid HTTP (")


def test_protocols_answer_beyond_the_limit_in_json(small_server):
    held = [socket.create_connection(("127.0.0.1", small_server)) for _ in range(2)]
    try:
        time.sleep(0.3)
        assert_json_error(exchange(small_server, b"GET / HTTP/1.1\r\nHost: t\r\n\r\n"), 503)
    finally:
        for sock in held:
            sock.close()


def test_protocols_answer_a_head_that_does_not_come_in_time_with_408(small_server):
    answer = exchange(small_server, b"GET / HTTP/1.1\r\nHost: t\r\n", timeout=SOCKET_TIMEOUT)
    assert "RANGERET_HEADER_TIMEOUT_S" in assert_json_error(answer, 408)


def test_protocols_answer_a_head_over_the_limit_with_431(small_server):
    head = b"GET / HTTP/1.1\r\nHost: t\r\n" + b"X-Filler: " + b"a" * 100_000 + b"\r\n\r\n"
    assert_json_error(exchange(small_server, head), 431)


def test_protocols_take_a_large_body_sent_with_its_head(small_server):
    request = b"POST / HTTP/1.1\r\nHost: t\r\nContent-Length: 300000\r\n\r\n" + b"x" * 300_000
    with socket.create_connection(("127.0.0.1", small_server), timeout=SOCKET_TIMEOUT) as sock:
        sock.sendall(request)
        assert sock.recv(65536).startswith(b"HTTP/1.1 200")


def test_protocols_close_a_connection_that_sends_nothing(small_server):
    with socket.create_connection(("127.0.0.1", small_server), timeout=SOCKET_TIMEOUT) as sock:
        assert sock.recv(65536) == b"", "closed without an answer"


def test_protocols_bound_the_head_of_a_later_request_too(small_server):
    with socket.create_connection(("127.0.0.1", small_server), timeout=SOCKET_TIMEOUT) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\nHost: t\r\n\r\n")
        assert sock.recv(65536).startswith(b"HTTP/1.1 200")
        sock.sendall(b"GET / HTTP/1.1\r\nHost: t\r\n")
        assert_json_error(read_answer(sock), 408)


def test_protocols_close_a_connection_whose_body_never_comes(small_server):
    request = b"POST / HTTP/1.1\r\nHost: t\r\nContent-Length: 100\r\n\r\n0123456789"
    answer = exchange(small_server, request, timeout=10)
    assert answer.status == 200 and answer.body == b"ok" and answer.closed


def test_protocols_keep_a_connection_whose_body_came(small_server):
    with socket.create_connection(("127.0.0.1", small_server), timeout=10) as sock:
        for _ in range(2):
            sock.sendall(b"POST / HTTP/1.1\r\nHost: t\r\nContent-Length: 3\r\n\r\nabc")
            assert sock.recv(65536).startswith(b"HTTP/1.1 200")
        time.sleep(1)  # past the wait for a body left unread
        sock.sendall(b"GET / HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n")
        assert read_answer(sock).status == 200


# Deadlines of the body readers -----------------------------------------------------------------


def trickle(
    first: bytes, headers: dict[str, str], hang: float = 3600
) -> tuple[Request, list[float]]:
    """A request whose body sends `first`, then nothing for `hang` seconds; and the times at
    which it was asked for more."""
    asked: list[float] = []
    sent = False

    async def receive() -> dict:
        nonlocal sent
        asked.append(time.monotonic())
        if not sent:
            sent = True
            return {"type": "http.request", "body": first, "more_body": True}
        await asyncio.sleep(hang)
        return {"type": "http.request", "body": b"", "more_body": False}

    scope = {
        "type": "http",
        "method": "POST",
        "path": "/",
        "query_string": b"",
        "headers": [(k.lower().encode(), v.encode()) for k, v in headers.items()],
    }
    return Request(scope, receive), asked


def test_read_body_answers_408_past_its_deadline():
    request, _ = trickle(b"x" * 10, {"Content-Length": "100"})
    start = time.monotonic()
    with pytest.raises(ApiError) as info:
        asyncio.run(read_body(request, 1000, 0.3))
    assert time.monotonic() - start < 5
    assert info.value.status_code == 408
    assert info.value.headers["Connection"] == "close"
    assert "RANGERET_BODY_TIMEOUT_S" in info.value.detail and "0.3 seconds" in info.value.detail


def test_read_body_within_its_deadline():
    request, _ = trickle(b"x" * 10, {"Content-Length": "10"}, hang=0)
    assert asyncio.run(read_body(request, 1000, 5)) == b"x" * 10


def test_receive_archive_answers_408_past_its_deadline(tmp_path):
    form = b'--b\r\nContent-Disposition: form-data; name="archive"; filename="a"\r\n\r\nPK'
    request, _ = trickle(form, {"Content-Type": "multipart/form-data; boundary=b"})
    with pytest.raises(ApiError) as info:
        asyncio.run(receive_archive(request, tmp_path / "upload", 1000, 0.3))
    assert info.value.status_code == 408
    assert "RANGERET_UPLOAD_TIMEOUT_S" in info.value.detail


def test_drain_stops_at_its_deadline():
    request, _ = trickle(b"x" * 10, {"Content-Length": "100"})
    start = time.monotonic()
    assert asyncio.run(drain(request, 1000, timeout=0.3)) is False
    assert time.monotonic() - start < 5


def test_oversized_body_that_stalls_is_413_and_closes():
    request, _ = trickle(b"x" * 200, {})
    with pytest.raises(ApiError) as info:
        asyncio.run(read_body(request, 100, 0.3))
    assert info.value.status_code == 413
    assert info.value.headers["Connection"] == "close"
