"""POST /v1/scans with bodies that would decode past RANGERET_MAX_DECODED_BYTES, against a real
uvicorn process on 127.0.0.1: each hostile header is one sentence (413 naming the limit, or 400)
answered before anything is allocated, and a body within the limit is labelled with the gateway's
peak memory (VmHWM, from a reset of its high-water mark) one buffer of its decoded points above
where it was. (At most two bodies decode at once: tests/service/test_scan_bodies.py.)"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from tests.support.gateway import Gateway, assert_error, gateway_env, start_gateway
from tests.support.hostile_files import (
    WIDE_POINT,
    bad_lzf_pcd,
    colliding_pcd,
    count_bomb_pcd,
    huge_laz,
    short_ascii_pcd,
    vlr_bomb_las,
    wide_compressed_pcd,
    wide_ply_header,
)
from tests.support.memory import peak_growth, reset_peak, status_bytes
from tests.support.workers import small_weights

MIB = 1 << 20
LIMIT = 48 * MIB
PCD = {"Content-Type": "application/x-pcd"}
LAS = {"Content-Type": "application/vnd.las"}
PLY = {"Content-Type": "application/ply"}
#: Points of a wide body within the limit (4,096 bytes each: 39 MiB) and past it (50 MiB).
WITHIN, PAST = 10_000, 12_500


@pytest.fixture(scope="module")
def gateway(tmp_path_factory) -> Iterator[Gateway]:
    base = tmp_path_factory.mktemp("decoded-limits")
    env = gateway_env(base / "state", [base], RANGERET_MAX_DECODED_BYTES=str(LIMIT))
    gw = start_gateway(small_weights(base), env, base / "gateway.log")
    with gw.client() as client:  # the network's first passes, before any peak is measured
        for points in (500, WITHIN):
            answer = client.post("/v1/scans", content=wide_compressed_pcd(points), headers=PCD)
            assert answer.status_code == 200, answer.text
    yield gw
    gw.stop()


def _measured(gw: Gateway) -> int:
    """The gateway's resident set, its peak reset to it (the test skips where it cannot be)."""
    if not reset_peak(gw.proc.pid):
        pytest.skip("this kernel does not reset a process's peak resident set")
    return status_bytes(gw.proc.pid)["VmRSS"]


def test_hostile_headers_are_one_sentence_before_anything_is_allocated(gateway):
    past = (
        "The PCD scan would decode to 51,200,000 bytes (12,500 points of 4,096 bytes), over the "
        "limit of 50,331,648 (RANGERET_MAX_DECODED_BYTES)."
    )
    cases = [
        (wide_compressed_pcd(PAST), PCD, 413, past),
        (count_bomb_pcd(20_000_000), PCD, 413,
         "The PCD scan declares 20,000,000 values per point (its FIELDS with their COUNTs), over "
         "the limit of 4,096 a point may hold."),
        (huge_laz(2**40), LAS, 413,
         "The LAS scan declares 1,099,511,627,776 points, over the limit of 200,000 "
         "(RANGERET_MAX_POINTS)."),
        (wide_ply_header(150_000), PLY, 413,
         "The PLY scan would decode to 123,600,000 bytes (150,000 points of 824 bytes), over the "
         "limit of 50,331,648 (RANGERET_MAX_DECODED_BYTES)."),
        (vlr_bomb_las(1_000_000), LAS, 400,
         "The LAS scan is malformed: the LAS header declares 1,000,000 VLRs, but the 0 bytes "
         "between its header and its points (at 227 of 34,000) hold at most 0."),
        (colliding_pcd(), PCD, 400,
         "The PCD scan is malformed: the PCD fields 'i' and 'i__0000' both give the column "
         "'i__0000' (a field with COUNT n gives NAME__0000 .. NAME__n-1)."),
        (short_ascii_pcd(1, 20), PCD, 400,
         "The PCD scan is malformed: the ascii PCD data holds 1 point, the header declares 20 "
         "(the file is truncated)."),
    ]  # fmt: skip
    for overflowing in (False, True):
        corrupt = (
            "The PCD scan is malformed: the compressed PCD data does not decompress to the 1,024 "
            "bytes its size word declares (its LZF stream is corrupt)."
        )
        cases.append((bad_lzf_pcd(overflowing), PCD, 400, corrupt))
    before = _measured(gateway)
    with gateway.client() as client:
        for body, headers, status, detail in cases:
            answer = client.post("/v1/scans", content=body, headers=headers)
            assert assert_error(answer, status) == detail
        assert client.get("/healthz").status_code == 200
    growth = peak_growth(gateway.proc.pid, before)
    print(f"peak growth over {len(cases)} hostile bodies: {growth / MIB:.1f} MiB")
    assert growth < 8 * MIB, growth
    assert "Traceback" not in gateway.output()


def test_a_body_within_the_limit_is_labelled_within_a_small_multiple_of_it(gateway):
    body = wide_compressed_pcd(WITHIN)
    assert len(body) < 1 * MIB
    growths = []
    for _ in range(2):  # memory freed and reused can only hide growth: the larger one counts
        before = _measured(gateway)
        with gateway.client() as client:
            answer = client.post("/v1/scans", content=body, headers=PCD)
        assert answer.status_code == 200, answer.text
        assert len(np.frombuffer(answer.content, "<u4")) == WITHIN
        growths.append(peak_growth(gateway.proc.pid, before))
    decoded, growth = WITHIN * WIDE_POINT, max(growths)
    print(f"peak growth for one body decoding to {decoded / MIB:.0f} MiB: {growth / MIB:.1f} MiB")
    assert growth < 1.5 * decoded, growth  # one buffer of the decoded points, and little more
