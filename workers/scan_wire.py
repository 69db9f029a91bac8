"""The single-scan exchange between the gateway and the Serve application, written once for both.

A request is `POST <route prefix>/scans?knn=true|false&confidence=true|false` whose body is the
scan's bytes in the profile's point record, exactly as the gateway received them. The answer is
`application/octet-stream`: the raw labels (little-endian uint32, one per point), followed, when
confidences were asked for, by each point's confidence (little-endian float32). A scan the network
cannot take is answered 400 (malformed) or 422 (it cannot be projected) with `{"detail": ...}`.
`GET <route prefix>/info` describes the network the application serves.
"""

from __future__ import annotations

import numpy as np

from rangeret.inference.results import ScanPrediction

SCANS_PATH = "/scans"
INFO_PATH = "/info"
OCTET = "application/octet-stream"
#: Answer header: the number of points labelled.
POINTS_HEADER = "X-Rangeret-Points"
#: Answer header: "1" when the confidences follow the labels.
CONFIDENCE_HEADER = "X-Rangeret-Confidence"


def options_query(knn: bool, confidence: bool) -> dict[str, str]:
    """The query parameters of a labelling request."""
    return {"knn": str(knn).lower(), "confidence": str(confidence).lower()}


def query_flag(value: str | None, default: bool, name: str) -> bool:
    """A query parameter read as a bool (true/false, 1/0, yes/no); `ValueError` naming it
    otherwise."""
    if value is None:
        return default
    text = value.strip().lower()
    if text in ("true", "1", "yes"):
        return True
    if text in ("false", "0", "no"):
        return False
    raise ValueError(f"the query parameter {name} is true or false, got {value[:40]!r}")


def encode_labels(scan: ScanPrediction) -> tuple[bytes, dict[str, str]]:
    """The answer's body and headers for one labelled scan."""
    labels = np.ascontiguousarray(scan.labels, dtype="<u4")
    headers = {POINTS_HEADER: str(len(labels)), CONFIDENCE_HEADER: "0"}
    if scan.confidence is None:
        return labels.tobytes(), headers
    confidence = np.ascontiguousarray(scan.confidence, dtype="<f4")
    headers[CONFIDENCE_HEADER] = "1"
    return labels.tobytes() + confidence.tobytes(), headers


def decode_labels(body: bytes, headers: dict[str, str] | object, points: int) -> ScanPrediction:
    """One labelled scan from an answer for a scan of `points` points; `ValueError` saying what
    does not fit when the answer is not one."""
    get = headers.get  # type: ignore[attr-defined]
    with_confidence = get(CONFIDENCE_HEADER) == "1"
    counted = get(POINTS_HEADER)
    expected = points * 4 * (2 if with_confidence else 1)
    if counted is None:
        raise ValueError(
            f"the Serve application answered {len(body)} bytes without the {POINTS_HEADER} "
            f"header, for a scan of {points} points"
        )
    if counted != str(points) or len(body) != expected:
        raise ValueError(
            f"the Serve application answered {len(body)} bytes for {counted} points, not the "
            f"{expected} bytes of {points} points"
        )
    labels = np.frombuffer(body, dtype="<u4", count=points)
    confidence = (
        np.frombuffer(body, dtype="<f4", count=points, offset=points * 4)
        if with_confidence
        else None
    )
    return ScanPrediction(labels, confidence)
