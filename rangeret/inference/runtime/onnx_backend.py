"""The onnxruntime backend: a network's forward pass in a session of its export, made once.

The first run of a set of weights exports the network (dynamic batch, the profile's resolution)
through `rangeret.inference.runtime.onnx_export.write_export`, which checks it against torch and writes it
atomically into the cache folder (`$RANGERET_CACHE/onnx`, else `~/.cache/rangeret/onnx`) under a
name keyed by the checkpoint's SHA-256, the network, the resolution, the batch and the rest of
what the file records; later runs, other processes and other actors load that file. The export
takes minutes for a full-size network and the exporter reports nothing meanwhile, so it is
announced with its cache file, followed by a "still exporting" line every `HEARTBEAT_S` seconds
(`export_heartbeat(False)` for -q) and closed with the time it took. Everything around the
forward pass (projection, kNN, raw ids) is the predictor's one code path.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import threading
import time
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path

import numpy as np
import torch

from rangeret.dataset.profiles import DatasetProfile
from rangeret.exceptions import RangeRetError
from rangeret.extras import require_extra
from rangeret.inference.runtime.onnx_export import (
    INPUT_NAME,
    OUTPUT_NAME,
    load_model,
    metadata_of,
    onnx_metadata,
    weights_digest_problem,
    write_export,
)
from rangeret.inference.runtime.onnx_session import make_session
from rangeret.io.regular_files import read_regular

log = logging.getLogger(__name__)

#: The environment variable naming the cache folder (its `onnx/` holds the exports).
CACHE_VARIABLE = "RANGERET_CACHE"
#: Seconds between two "still exporting" lines while an export runs.
HEARTBEAT_S = 15.0
#: Whether exports say "still exporting" while they run (`export_heartbeat`).
_HEARTBEAT: ContextVar[bool] = ContextVar("onnx_export_heartbeat", default=True)


def cache_dir() -> Path:
    """Where exports are cached: `$RANGERET_CACHE/onnx`, else `~/.cache/rangeret/onnx` (under
    `$XDG_CACHE_HOME` when set)."""
    root = os.environ.get(CACHE_VARIABLE, "").strip()
    if root:
        return Path(root).expanduser() / "onnx"
    base = os.environ.get("XDG_CACHE_HOME", "").strip() or "~/.cache"
    return Path(base).expanduser() / "rangeret" / "onnx"


def state_sha256(network: torch.nn.Module) -> str:
    """SHA-256 of a network's weights, in key order: the key of networks that come from no file."""
    digest = hashlib.sha256()
    for key, value in network.state_dict().items():
        digest.update(key.encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def export_path(network: torch.nn.Module, profile: DatasetProfile, sha: str) -> Path:
    """The cache file of the dynamic-batch export of `network` (weights of SHA-256 `sha`) for
    `profile`."""
    record = onnx_metadata(network, profile, dynamic_batch=True, checkpoint_sha256=sha)
    key = hashlib.sha256(
        json.dumps({**record, "torch": torch.__version__}, sort_keys=True).encode()
    ).hexdigest()
    p = profile.projection
    return (
        cache_dir()
        / f"{network.config.name}-{p.height}x{p.width}-nbatch-{sha[:16]}-{key[:12]}.onnx"
    )


#: What a cached export must record as asked for before it runs: the weights, the network, the
#: sensor's projection and the profile.
CHECKED_FIELDS = ("checkpoint_sha256", "network", "network_config", "projection", "profile")


def export_mismatch(source: Path | bytes, expected: dict) -> str | None:
    """Why the export at `source` (its file or bytes) is not the one `expected` describes (its
    weights' SHA-256 named, with the one asked for), or None when its metadata agrees on
    `CHECKED_FIELDS` and its graph holds the weights its metadata records a digest of."""
    return _inspect(source, expected)[1]


def _inspect(source: Path | bytes, expected: dict) -> tuple[dict | None, str | None]:
    """An export's metadata (None where it has none) and why it is not the one `expected`
    describes (None when it is: see `export_mismatch`), its model parsed once."""
    try:
        proto = load_model(source)
        found = metadata_of(proto, "the model" if isinstance(source, bytes) else str(source))
    except ValueError as exc:
        return None, str(exc)
    if found.get("checkpoint_sha256") != expected["checkpoint_sha256"]:
        return found, (
            f"was made from checkpoint sha256 {found.get('checkpoint_sha256')}, not from "
            f"sha256 {expected['checkpoint_sha256']}"
        )
    for field in CHECKED_FIELDS[1:]:
        if found.get(field) != expected[field]:
            return found, f"records another {field.replace('_', ' ')} than the one asked for"
    return found, weights_digest_problem(proto, found)


def cached_export(
    network: torch.nn.Module, profile: DatasetProfile, checkpoint_sha256: str | None
) -> Path:
    """The cached export of `network` for `profile` (`checked_cache`)."""
    return checked_cache(network, profile, checkpoint_sha256)[0]


def checked_cache(
    network: torch.nn.Module, profile: DatasetProfile, checkpoint_sha256: str | None
) -> tuple[Path, bytes]:
    """The cached export of `network` for `profile` and the bytes of it that were checked, made
    (and checked) first if missing, and made again when the file there records other weights,
    network, projection or profile than these (a file copied over another); weights that come
    from no file are known by `state_sha256`. Without the onnx extra, `MissingExtraError`
    before anything is exported."""
    require_extra("--backend onnxruntime", "onnx")
    sha = checkpoint_sha256 or state_sha256(network)
    path = export_path(network, profile, sha)
    expected = onnx_metadata(network, profile, dynamic_batch=True, checkpoint_sha256=sha)
    if path.exists():
        data = read_regular(path, "an ONNX export")
        problem = export_mismatch(data, expected)
        if problem is None:
            return path, data
        log.warning("the cached export %s %s: exporting it again", path, problem)
    with export_progress(network.config.name, path):
        check = write_export(network, profile, path, dynamic_batch=True, checkpoint_sha256=sha)
    log.info("%s", check.text())
    data = read_regular(path, "an ONNX export")
    problem = export_mismatch(data, expected)
    if problem is not None:  # replaced since it was written
        raise ExportFileError(f"the export {path} {problem}")
    return path, data


class ExportFileError(RangeRetError, ValueError):
    """An export given with `--onnx` that cannot run this network: one sentence naming it."""


def given_export(
    path: Path,
    network: torch.nn.Module,
    profile: DatasetProfile,
    checkpoint_sha256: str | None,
    batch_size: int,
) -> bytes:
    """The bytes of `path`, an export `rangeret export` wrote, read once and checked: they must
    record these weights, network, projection and profile, hold the weights they record, and
    take batches of `batch_size`; an `ExportFileError` naming what differs otherwise."""
    require_extra("--backend onnxruntime", "onnx")
    if not path.exists():
        raise ExportFileError(f"--onnx {path}: no such file")
    sha = checkpoint_sha256 or state_sha256(network)
    expected = onnx_metadata(network, profile, dynamic_batch=True, checkpoint_sha256=sha)
    try:
        data = read_regular(path, "an ONNX export")
    except ValueError as exc:
        raise ExportFileError(f"--onnx {exc}") from None
    found, problem = _inspect(data, expected)
    if problem is not None:
        raise ExportFileError(
            f"--onnx {path} {problem}: export this checkpoint again with rangeret export, or "
            "leave --onnx out to use the cached export"
        )
    if batch_size > 1 and not (found or {}).get("dynamic_batch"):
        raise ExportFileError(
            f"--onnx {path} takes batches of 1 scan and this run makes batches of {batch_size}: "
            "export it with --dynamic-batch, or pass --batch-size 1"
        )
    return data


@contextlib.contextmanager
def export_heartbeat(enabled: bool) -> Iterator[None]:
    """Whether exports made inside say "still exporting (N s)" while they run (off for -q);
    the lines before and after an export are logged either way."""
    token = _HEARTBEAT.set(enabled)
    try:
        yield
    finally:
        _HEARTBEAT.reset(token)


@contextlib.contextmanager
def export_progress(name: str, path: Path, interval: float | None = None) -> Iterator[None]:
    """Log an export of network `name` into `path`: a line before, one every `interval` seconds
    while it runs (default `HEARTBEAT_S`; none under `export_heartbeat(False)`), since the
    exporter reports nothing for minutes, and one with the time taken once it is written."""
    interval = HEARTBEAT_S if interval is None else interval
    started = time.monotonic()
    log.info("exporting %s to ONNX for onnxruntime (first use; cached at %s)", name, path)
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(interval):
            log.info("still exporting %s to ONNX (%.0f s)", name, time.monotonic() - started)

    beats = threading.Thread(target=beat, name="onnx-export-progress", daemon=True)
    if _HEARTBEAT.get():
        beats.start()
    try:
        yield
    finally:
        stop.set()
        if beats.is_alive():
            beats.join()
    log.info(
        "exported %s to ONNX in %.0f s; later runs load %s", name, time.monotonic() - started, path
    )


class OnnxForward:
    """A network's forward pass in onnxruntime on `device`: (B, 5, H, W) -> (B, C, H, W) logits,
    float32, on the input's device."""

    def __init__(
        self,
        network: torch.nn.Module,
        profile: DatasetProfile,
        device: torch.device,
        checkpoint_sha256: str | None,
        *,
        export: Path | None = None,
        batch_size: int = 1,
    ) -> None:
        # The bytes that run are the bytes checked: read once, checked, then loaded.
        if export is None:
            self.path, data = checked_cache(network, profile, checkpoint_sha256)
        else:
            self.path = export
            data = given_export(export, network, profile, checkpoint_sha256, batch_size)
        try:
            self.session = make_session(data, device)
        except ValueError:
            raise
        except Exception as exc:  # onnxruntime's load errors have no common base class
            raise ValueError(
                f"onnxruntime cannot load the cached export {self.path} ({exc}); delete it to "
                "export again"
            ) from exc

    def __call__(self, batch: torch.Tensor) -> torch.Tensor:
        """Logits of a batch of normalised range images."""
        image = np.ascontiguousarray(batch.detach().cpu().numpy(), dtype=np.float32)
        logits = self.session.run([OUTPUT_NAME], {INPUT_NAME: image})[0]
        return torch.from_numpy(logits).to(batch.device)
