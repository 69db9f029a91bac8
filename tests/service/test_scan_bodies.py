"""The gateway's file bodies: the limits named by their settings, what each refusal answers, and at
most `DECODE_SLOTS` bodies decoding at once however many threads ask."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from rangeret.dataset.profiles import load_profile
from service.http.errors import ApiError
from service.labelling import scan_bodies
from service.labelling.scan_bodies import DECODE_SLOTS, body_limits, decode_file_body
from service.settings import Settings
from tests.support.hostile_files import count_bomb_pcd, wide_compressed_pcd
from tests.support.point_files import pcd_bytes

PROFILE = load_profile("semantickitti")


def test_limits_come_from_the_settings_and_name_them():
    limits = body_limits(Settings(max_decoded_bytes=1_000_000, max_points=5_000))
    with pytest.raises(ApiError) as exc:
        decode_file_body(wide_compressed_pcd(300), "pcd", PROFILE, limits)
    assert exc.value.status_code == 413 and exc.value.detail == (
        "The PCD scan would decode to 1,228,800 bytes (300 points of 4,096 bytes), over the "
        "limit of 1,000,000 (RANGERET_MAX_DECODED_BYTES)."
    )
    with pytest.raises(ApiError) as exc:
        decode_file_body(count_bomb_pcd(), "pcd", PROFILE, limits)
    assert exc.value.status_code == 413 and "20,000,000 values per point" in exc.value.detail
    many = pcd_bytes(np.ones((5_001, 4), np.float32), "binary")
    with pytest.raises(ApiError) as exc:
        decode_file_body(many, "pcd", PROFILE, limits)
    assert exc.value.detail == (
        "The PCD scan declares 5,001 points, over the limit of 5,000 (RANGERET_MAX_POINTS)."
    )
    body = decode_file_body(wide_compressed_pcd(200), "pcd", PROFILE, limits)
    assert body.num_points == 200 and body.points.shape == (200, 4)


def test_the_default_is_the_library_s(monkeypatch):
    monkeypatch.delenv("RANGERET_MAX_DECODED_BYTES", raising=False)
    assert Settings().max_decoded_bytes == 256 << 20
    monkeypatch.setenv("RANGERET_MAX_DECODED_BYTES", "1234")
    assert body_limits(Settings()).max_decoded_bytes == 1234


def test_at_most_decode_slots_bodies_decode_at_once(monkeypatch):
    busy, most, lock = 0, 0, threading.Lock()

    def slow(*args):
        nonlocal busy, most
        with lock:
            busy += 1
            most = max(most, busy)
        time.sleep(0.05)
        with lock:
            busy -= 1
        return "decoded"

    monkeypatch.setattr(scan_bodies, "_decoded", slow)
    limits = body_limits(Settings())
    with ThreadPoolExecutor(8) as pool:
        done = list(pool.map(lambda _: decode_file_body(b"", "pcd", PROFILE, limits), range(16)))
    assert done == ["decoded"] * 16
    assert most == DECODE_SLOTS == 2
