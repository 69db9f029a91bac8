"""POST /v1/scans with point-cloud file bodies, against a real uvicorn process on 127.0.0.1.

A PCD and a LAZ body (by Content-Type, or by signature under application/octet-stream) get the
labels `rangeret predict --files` writes for the same files, in the body's point order; a
declared point count over the gateway's (here tiny) limit is a 413 before the body is decoded or
decompressed; malformed bodies and unknown media types are one-sentence 4xx answers.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

import numpy as np
import pytest
import torch

from rangeret.cli.main import main as rangeret_main
from rangeret.io import las, pcd
from rangeret.io.scans import read_labels, read_scan
from tests.support.gateway import Gateway, assert_error, gateway_env, start_gateway
from tests.support.point_files import las_bytes, pcd_bytes
from tests.support.workers import small_weights

LIMIT = 6000
NET = ["--height", "32", "--width", "256", "--device", "cpu", "-q"]


@pytest.fixture(scope="module")
def files(tmp_path_factory, real_scan_path) -> dict:
    """A 4,936-point subsample of the real scan as a compressed PCD (with two NaN points) and as
    LAZ, with the labels `rangeret predict --files` gives them."""
    base = tmp_path_factory.mktemp("gateway-files")
    weights = small_weights(base)
    points = read_scan(real_scan_path)[::25].copy()
    with_nan = points.copy()
    with_nan[[5, 100]] = np.nan
    paths = {"pcd": base / "scan-pcd.pcd", "laz": base / "scan-laz.laz"}
    paths["pcd"].write_bytes(pcd_bytes(with_nan, "binary_compressed"))
    paths["laz"].write_bytes(las_bytes(points, compressed=True))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        args = ["predict", "--files", *map(str, paths.values()), "--out", str(base / "ref")]
        assert rangeret_main([*args, "--checkpoint", str(weights), *NET]) == 0
    finally:
        torch.set_num_threads(threads)
    return {"base": base, "weights": weights, "paths": paths, "ref": base / "ref"}


@pytest.fixture(scope="module")
def gateway(files) -> Iterator[Gateway]:
    env = gateway_env(files["base"] / "state", [files["base"]], RANGERET_MAX_POINTS=str(LIMIT))
    gw = start_gateway(files["weights"], env, files["base"] / "gateway.log")
    yield gw
    gw.stop()


def test_pcd_and_laz_bodies_get_the_labels_of_rangeret_predict(files, gateway):
    with gateway.client() as client:
        for kind, media in (("pcd", "application/x-pcd"), ("laz", "application/vnd.laszip")):
            path = files["paths"][kind]
            body, expected = path.read_bytes(), read_labels(files["ref"] / f"{path.stem}.label")
            for content_type in (media, "application/octet-stream"):  # by type, by signature
                answer = client.post(
                    "/v1/scans", content=body, headers={"Content-Type": content_type}
                )
                assert answer.status_code == 200, answer.text
                assert np.array_equal(np.frombuffer(answer.content, "<u4"), expected), kind
            as_json = client.post(
                "/v1/scans",
                params={"confidence": "true"},
                content=body,
                headers={"Content-Type": media, "Accept": "application/json"},
            ).json()
            assert as_json["num_points"] == 4936 and as_json["labels"] == expected.tolist()
            if kind == "pcd":  # the NaN points: unlabelled (raw 0), confidence 0, in place
                assert as_json["labels"][5] == as_json["labels"][100] == 0
                assert as_json["confidence"][5] == as_json["confidence"][100] == 0
                assert sum(as_json["class_counts"].values()) == 4936


def _forged_pcd(points: int) -> bytes:
    """A compressed PCD whose header declares `points` and whose data cannot decompress."""
    data = pcd_bytes(np.ones((64, 4), np.float32), "binary_compressed")
    head = data[: pcd.parse_header(data, "x").data_offset].decode()
    head = head.replace("WIDTH 64", f"WIDTH {points}").replace("POINTS 64", f"POINTS {points}")
    return head.encode() + struct.pack("<II", 200, points * 16) + b"\xff" * 200


def _forged_laz(files: dict, points: int) -> bytes:
    """The LAZ file with `points` in its header and its compressed points overwritten."""
    data = bytearray(files["paths"]["laz"].read_bytes())
    start = las.read_las(bytes(data), "x").data.header.offset_to_point_data
    data[107:111] = struct.pack("<I", points)  # LAS 1.2: the legacy point count
    data[start + 8 : start + 400] = b"\xff" * 392
    return bytes(data)


def test_a_declared_count_over_the_limit_is_refused_before_decoding(files, gateway):
    pcd_type = {"Content-Type": "application/x-pcd"}
    laz_type = {"Content-Type": "application/vnd.laszip"}
    with gateway.client() as client:
        detail = assert_error(
            client.post("/v1/scans", content=_forged_pcd(6001), headers=pcd_type), 413
        )
        assert "declares 6,001 points" in detail and "limit of 6,000" in detail
        detail = assert_error(
            client.post("/v1/scans", content=_forged_laz(files, 6001), headers=laz_type), 413
        )
        assert "declares 6,001 points" in detail
        # The same bodies within the limit are decoded, and found malformed.
        detail = assert_error(
            client.post("/v1/scans", content=_forged_pcd(64), headers=pcd_type), 400
        )
        assert detail.startswith("The PCD scan is malformed")
        detail = assert_error(
            client.post("/v1/scans", content=_forged_laz(files, 5000), headers=laz_type), 400
        )
        assert "LAZ" in detail


def test_malformed_bodies_and_unknown_types_are_one_sentence(files, gateway):
    body = files["paths"]["pcd"].read_bytes()
    with gateway.client() as client:
        detail = assert_error(
            client.post(
                "/v1/scans", content=body[:-500], headers={"Content-Type": "application/x-pcd"}
            ),
            400,
        )
        assert "truncated" in detail
        ply = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n2\n"
        detail = assert_error(
            client.post("/v1/scans", content=ply, headers={"Content-Type": "application/ply"}), 400
        )
        assert "fields do not fill the semantickitti point record" in detail and "no y" in detail
        detail = assert_error(
            client.post("/v1/scans", content=body, headers={"Content-Type": "text/plain"}), 415
        )
        assert "application/x-pcd" in detail and "application/vnd.laszip" in detail
        # A .bin body under application/octet-stream stays a .bin body.
        records = np.ones((50, 4), np.float32).tobytes()
        answer = client.post(
            "/v1/scans", content=records, headers={"Content-Type": "application/octet-stream"}
        )
        assert answer.status_code == 200 and len(answer.content) == 200
