"""ONNX exports of a loaded network: the graph, the metadata a consumer needs, and the check.

`export_onnx` exports a network with torch's dynamo-based exporter (the legacy TorchScript one
cannot trace these networks) at the resolution of the profile it runs with, for batch 1 or a
dynamic batch, and writes into the model's `metadata_props` everything a consumer needs besides
the graph: the profile, its label configuration (class names, raw ids), the input normalisation,
the projection, the network and its blocks, the input and output names and layouts
((N, 5, H, W) -> (N, C, H, W)), the checkpoint's SHA-256 and this project's version, each value
as JSON under a `rangeret.` key. `read_metadata` reads them back as plain data.

The metadata also records the digest of the graph's own weights (`initializers_sha256`, over every
initializer's name, type, shape and bytes). Metadata copied into another graph names the
checkpoint it was copied from, but not that graph's weights: a consumer computes the digest of
the initializers it loads (`weights_digest_problem`) and refuses a graph whose digest differs.

`check_export` runs the export in onnxruntime and the network in torch (fp32) on the same inputs:
a projected scan (a given one, else a simulated street scan of the profile's sensor) and
fixed-seed noise, one at a time and, for a dynamic batch, together. `write_export` exports,
checks and writes the file atomically only when the largest logit difference is within
`MAX_LOGIT_DIFFERENCE`; `rangeret export` and the onnxruntime backend's cache both go through it.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import logging
import warnings
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rangeret import __version__
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.projection import project_with
from rangeret.exceptions import ModelError
from rangeret.extras import require_extra
from rangeret.inference.settings import DEFAULT_KNN
from rangeret.io.atomic import atomic_write_bytes
from rangeret.io.regular_files import read_regular

if TYPE_CHECKING:
    import onnx
    import torch

#: Names of the graph's input and output.
INPUT_NAME = "range_image"
OUTPUT_NAME = "logits"

#: Prefix of the metadata keys this project writes; each value is JSON.
METADATA_PREFIX = "rangeret."
METADATA_VERSION = 1
#: The metadata key of the digest of the graph's own weights (`initializers_sha256`).
INITIALIZERS_KEY = "initializers_sha256"

#: Largest |logit difference| between onnxruntime and torch an export may show to be written.
MAX_LOGIT_DIFFERENCE = 1e-3

#: Seed of the check's simulated scan and noise.
CHECK_SEED = 2026

#: The five input channels, in order.
CHANNELS = ("range", "x", "y", "z", "remission")


class ExportError(ModelError, ValueError):
    """An export that could not be made, or that onnxruntime does not run as torch does."""


@dataclass(frozen=True)
class ExportCheck:
    """How the export's logits compare with torch's on the check's inputs."""

    max_difference: float
    agreement: float
    pixels: int
    inputs: str

    @property
    def ok(self) -> bool:
        """Whether the largest difference is within `MAX_LOGIT_DIFFERENCE`."""
        return self.max_difference <= MAX_LOGIT_DIFFERENCE

    def text(self) -> str:
        """One line: the largest logit difference and the argmax agreement."""
        return (
            f"onnxruntime vs torch on {self.inputs}: max |logit difference| "
            f"{self.max_difference:.2e}, argmax equal on {100 * self.agreement:.3f} % of "
            f"{self.pixels:,} pixels"
        )


def onnx_metadata(
    network: torch.nn.Module,
    profile: DatasetProfile,
    *,
    dynamic_batch: bool,
    checkpoint_sha256: str | None,
) -> dict[str, Any]:
    """The plain-data record an export carries (without the `rangeret.` prefix of its keys)."""
    p, labels, config = profile.projection, profile.labels, network.config
    batch: str | int = "N" if dynamic_batch else 1
    return {
        "format_version": METADATA_VERSION,
        "profile": profile.name,
        "class_names": list(labels.class_names),
        "class_raw_ids": list(labels.class_raw_ids),
        "label_config": profile.to_dict()["labels"],
        "means": list(p.means),
        "stds": list(p.stds),
        "projection": {
            "height": p.height,
            "width": p.width,
            "fov_up": p.fov_up,
            "fov_down": p.fov_down,
            "row": p.row,
        },
        "point_fields": list(profile.points.fields),
        "knn": {"votes_from": profile.knn.votes_from, **asdict(DEFAULT_KNN)},
        "network": config.name,
        "blocks": config.layers,
        "network_config": config.to_dict(),
        "input": {
            "name": INPUT_NAME,
            "layout": "N,5,H,W",
            "shape": [batch, len(CHANNELS), p.height, p.width],
            "dtype": "float32",
            "channels": list(CHANNELS),
            "normalisation": "(value - mean) / std per channel, 0 on pixels without a point",
        },
        "output": {
            "name": OUTPUT_NAME,
            "layout": "N,C,H,W",
            "shape": [batch, labels.num_classes, p.height, p.width],
            "dtype": "float32",
        },
        "dynamic_batch": dynamic_batch,
        "checkpoint_sha256": checkpoint_sha256,
        "version": __version__,
    }


def export_onnx(
    network: torch.nn.Module,
    profile: DatasetProfile,
    *,
    dynamic_batch: bool,
    checkpoint_sha256: str | None,
) -> bytes:
    """The serialized ONNX model of `network` at the profile's resolution, with its metadata;
    `MissingExtraError` without the onnx extra (the exporter needs onnx and onnxscript)."""
    import torch

    require_extra("ONNX export", "onnx")
    p = profile.projection
    model = copy.deepcopy(network).cpu().eval()  # the trace fills the copy's decay tables only
    generator = torch.Generator().manual_seed(CHECK_SEED)
    # An example batch of 1 would make the exporter fix the batch; 2 leaves it free.
    example = torch.randn(
        2 if dynamic_batch else 1, len(CHANNELS), p.height, p.width, generator=generator
    )
    dynamic = ({0: torch.export.Dim("batch", min=1)},) if dynamic_batch else None
    try:
        with _quiet_exporter():
            program = torch.onnx.export(
                model,
                (example,),
                dynamo=True,
                input_names=[INPUT_NAME],
                output_names=[OUTPUT_NAME],
                dynamic_shapes=dynamic,
                verbose=False,
            )
    except Exception as exc:  # the exporter's own errors are many; the reason is their first line
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ExportError(f"torch could not export {model.config.name} to ONNX: {reason}") from exc
    proto = program.model_proto
    record = onnx_metadata(
        network, profile, dynamic_batch=dynamic_batch, checkpoint_sha256=checkpoint_sha256
    )
    record[INITIALIZERS_KEY] = initializers_sha256(proto)
    for key, value in record.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = METADATA_PREFIX + key, json.dumps(value)
    proto.doc_string = (
        f"RangeRet {model.config.name} for the {profile.name} profile: (N, 5, H, W) normalised "
        f"range images -> (N, C, H, W) logits; see the {METADATA_PREFIX}* metadata"
    )
    return proto.SerializeToString()


def initializers_sha256(proto: onnx.ModelProto) -> str:
    """SHA-256 over a graph's initializers in name order: each one's name, element type, shape
    and values (little-endian bytes, whatever their storage in the file)."""
    from onnx import numpy_helper

    digest = hashlib.sha256()
    for tensor in sorted(proto.graph.initializer, key=lambda t: t.name):
        values = np.ascontiguousarray(numpy_helper.to_array(tensor))
        digest.update(json.dumps([tensor.name, tensor.data_type, list(tensor.dims)]).encode())
        digest.update(values.astype(values.dtype.newbyteorder("<"), copy=False).tobytes())
    return digest.hexdigest()


def weights_digest_problem(proto: onnx.ModelProto, record: dict[str, Any]) -> str | None:
    """Why a graph's weights are not the ones its metadata `record` vouches for (their digest
    differs, or the record holds none), or None when they are."""
    recorded = record.get(INITIALIZERS_KEY)
    if not isinstance(recorded, str):
        return "records no digest of its weights (it predates them, or was not made by rangeret export)"
    found = initializers_sha256(proto)
    if found != recorded:
        return (
            f"holds weights of digest {found[:16]}, not the {recorded[:16]} its metadata records: "
            "its metadata was copied from another export"
        )
    return None


def load_model(source: Path | bytes) -> onnx.ModelProto:
    """An ONNX model, weights included, from its file or bytes; `ExportError` naming it when it
    is not one (a file that is not a regular one is refused by its kind first)."""
    import onnx

    name = "the model" if isinstance(source, bytes) else str(source)
    data = source if isinstance(source, bytes) else read_regular(source, "an ONNX export")
    try:
        return onnx.load_from_string(data)
    except Exception as exc:  # onnx's parse errors have no common base class
        raise ExportError(f"{name} is not an ONNX model: {exc}") from exc


def metadata_of(proto: onnx.ModelProto, name: str) -> dict[str, Any]:
    """The `rangeret.` metadata of a loaded model as plain data, keys without the prefix;
    `ExportError` naming it when it has none."""
    record = {
        entry.key.removeprefix(METADATA_PREFIX): json.loads(entry.value)
        for entry in proto.metadata_props
        if entry.key.startswith(METADATA_PREFIX)
    }
    if not record:
        raise ExportError(
            f"{name} carries no {METADATA_PREFIX}* metadata: it is not a RangeRet export"
        )
    return record


def read_metadata(source: str | Path | bytes) -> dict[str, Any]:
    """The `rangeret.` metadata of an ONNX model (its file or bytes) as plain data, keys without
    the prefix; ValueError naming the file when it is not an ONNX model or has none."""
    import onnx

    name = "the model" if isinstance(source, bytes) else str(source)
    try:
        proto = (
            onnx.load_from_string(source)
            if isinstance(source, bytes)
            else onnx.load(str(source), load_external_data=False)
        )
    except FileNotFoundError:
        raise
    except Exception as exc:
        raise ExportError(f"{name} is not an ONNX model: {exc}") from exc
    return metadata_of(proto, name)


def check_images(profile: DatasetProfile, scan: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """(K, 5, H, W) float32 inputs of the check and what they are: the projected `scan` (else a
    simulated street scan of the profile's sensor, where its point record allows one), then
    fixed-seed noise."""
    p = profile.projection
    noise = np.random.default_rng(CHECK_SEED).standard_normal((len(CHANNELS), p.height, p.width))
    noise = noise.astype(np.float32)
    what = "the given scan"
    if scan is None:
        scan, what = simulated_scan(profile), "a simulated street scan"
    if scan is None:
        return noise[None], "fixed-seed noise"
    image = project_with(scan, p).image
    return np.stack([image, noise]), f"{what} and fixed-seed noise"


def simulated_scan(profile: DatasetProfile) -> np.ndarray | None:
    """A street scan of the profile's sensor in its point record, or None for records the
    simulator does not write (anything but x, y, z, remission and an optional laser id or ring)."""
    from rangeret.sim import SensorConfig, beam_values, make_scene, simulate_scan

    if profile.points.fields[4:] not in ((), ("laser_id",), ("ring",)):
        return None
    rng = np.random.default_rng(CHECK_SEED)
    scene = make_scene(rng)
    points, _, lasers = simulate_scan(
        scene, 20.0, SensorConfig.for_profile(profile), rng, lasers=True
    )
    if profile.points.num_fields == 5:
        points = np.column_stack([points, beam_values(lasers, profile)])
    return points


def check_export(
    model: bytes,
    network: torch.nn.Module,
    profile: DatasetProfile,
    *,
    dynamic_batch: bool,
    scan: np.ndarray | None = None,
) -> ExportCheck:
    """The export's logits in onnxruntime (CPU) against the network's in torch (fp32, in eval
    mode, on its own device) on `check_images`: each input alone and, for a dynamic batch, all
    together."""
    import torch

    from rangeret.inference.runtime.onnx_session import make_session
    from rangeret.inference.runtime.precision import forward_precision

    images, inputs = check_images(profile, scan)
    session = make_session(model, torch.device("cpu"))
    batches = [images[i : i + 1] for i in range(len(images))]
    if dynamic_batch and len(images) > 1:
        batches.append(images)
    network.eval()
    device = next(network.parameters()).device
    worst, equal, pixels = 0.0, 0, 0
    for batch in batches:
        ours = session.run([OUTPUT_NAME], {INPUT_NAME: batch})[0]
        with torch.inference_mode(), forward_precision("fp32", device):
            theirs = network(torch.from_numpy(batch).to(device)).float().cpu().numpy()
        worst = max(worst, float(np.abs(ours - theirs).max()))
        equal += int((ours.argmax(1) == theirs.argmax(1)).sum())
        pixels += ours.shape[0] * ours.shape[2] * ours.shape[3]
    return ExportCheck(worst, equal / pixels, pixels, inputs)


def write_export(
    network: torch.nn.Module,
    profile: DatasetProfile,
    out: str | Path,
    *,
    dynamic_batch: bool,
    checkpoint_sha256: str | None,
    scan: np.ndarray | None = None,
) -> ExportCheck:
    """Export `network`, check it, and write `out` atomically when the check passes; an
    ExportError (one sentence with the figures) otherwise, and nothing written."""
    model = export_onnx(
        network, profile, dynamic_batch=dynamic_batch, checkpoint_sha256=checkpoint_sha256
    )
    check = check_export(model, network, profile, dynamic_batch=dynamic_batch, scan=scan)
    if not check.ok:
        raise ExportError(
            f"{out} was not written: {check.text()}, beyond the {MAX_LOGIT_DIFFERENCE:g} allowed"
        )
    atomic_write_bytes(out, model)
    return check


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence the exporter's warnings and log lines about other libraries and its tracing."""
    names = ("torch.onnx", "torch.export", "torch._dynamo", "onnxscript", "onnx_ir")
    loggers = [logging.getLogger(name) for name in names]
    levels = [logger.level for logger in loggers]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for logger in loggers:
            logger.setLevel(logging.ERROR)
        try:
            yield
        finally:
            for logger, level in zip(loggers, levels, strict=True):
                logger.setLevel(level)
