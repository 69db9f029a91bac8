"""The single-scan exchange between the gateway and the Serve application, written once for both.

A request is `POST <route prefix>/scans?knn=true|false&confidence=true|false&panoptic=true|false`
whose body is the scan's bytes in the profile's point record, exactly as the gateway received
them; a request without `panoptic` is answered as with `panoptic=false`. The answer is
`application/octet-stream`: the labels (little-endian uint32, one per point: raw ids, or with
`panoptic=true` the benchmark's panoptic labels, SemanticKITTI's `instance << 16 | raw id` or
nuScenes-panoptic's `1000 x class + instance`), followed, when confidences were asked for, by each
point's confidence (little-endian float32), then, with `panoptic=true`, by each point's object
(little-endian uint32, unique in the scan, 0 for stuff). The header `X-Rangeret-Instances`,
present exactly when the objects follow, gives how many there are. A scan the network cannot take
is answered 400 (malformed) or 422 (it cannot be projected) with `{"detail": ...}`, and a panoptic
request to a model whose profile names no thing class 400. `GET <route prefix>/info` describes the
network the application serves.
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
#: Answer header of a panoptic answer: the number of objects; the instances follow the labels
#: (and the confidences, when asked for).
INSTANCES_HEADER = "X-Rangeret-Instances"


def options_query(knn: bool, confidence: bool, panoptic: bool = False) -> dict[str, str]:
    """The query parameters of a labelling request."""
    return {
        "knn": str(knn).lower(),
        "confidence": str(confidence).lower(),
        "panoptic": str(panoptic).lower(),
    }


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
    """The answer's body and headers for one labelled scan (its objects after the labels and
    confidences when it has them)."""
    labels = np.ascontiguousarray(scan.labels, dtype="<u4")
    headers = {POINTS_HEADER: str(len(labels)), CONFIDENCE_HEADER: "0"}
    parts = [labels.tobytes()]
    if scan.confidence is not None:
        parts.append(np.ascontiguousarray(scan.confidence, dtype="<f4").tobytes())
        headers[CONFIDENCE_HEADER] = "1"
    if scan.instances is not None:
        parts.append(np.ascontiguousarray(scan.instances, dtype="<u4").tobytes())
        headers[INSTANCES_HEADER] = str(scan.num_instances)
    return b"".join(parts), headers


def decode_labels(body: bytes, headers: dict[str, str] | object, points: int) -> ScanPrediction:
    """One labelled scan from an answer for a scan of `points` points; `ValueError` saying what
    does not fit when the answer is not one."""
    get = headers.get  # type: ignore[attr-defined]
    with_confidence = get(CONFIDENCE_HEADER) == "1"
    objects = _object_count(get(INSTANCES_HEADER))
    counted = get(POINTS_HEADER)
    arrays = 1 + with_confidence + (objects is not None)
    expected = points * 4 * arrays
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
    instances = (
        np.frombuffer(body, dtype="<u4", count=points, offset=points * 4 * (arrays - 1))
        if objects is not None
        else None
    )
    scan = ScanPrediction(labels, confidence, instances=instances)
    if objects is not None and scan.num_instances != objects:
        raise ValueError(
            f"the Serve application answered {scan.num_instances} objects, not the {objects} "
            f"of its {INSTANCES_HEADER} header"
        )
    return scan


def _object_count(value: str | None) -> int | None:
    """The object count of an `INSTANCES_HEADER` (None: no objects follow); `ValueError` when
    it is not a count."""
    if value is None:
        return None
    text = value.strip()
    if not (text.isascii() and text.isdigit()):
        raise ValueError(
            f"the Serve application's {INSTANCES_HEADER} header is not a count: {value[:40]!r}"
        )
    return int(text)
