"""Published weights from the model hub: the local cache first, else a download.

Downloads go through `huggingface_hub`, so `HF_ENDPOINT` (a mirror), `HF_HOME` and
`HF_HUB_CACHE` (where the cache lies), `HF_HUB_OFFLINE` and the hub's tokens (`HF_TOKEN`,
`huggingface-cli login`) behave as users of that ecosystem expect. A download is written to a
temporary file and moved into place only once whole, so a partial file is never used; a file
whose SHA-256 differs from the registry's pin is refused and removed. A hub that cannot be
reached gets one sentence naming the URL and where to put the file by hand.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rangeret.dataset.profiles import DatasetProfile
from rangeret.exceptions import ModelError
from rangeret.extras import extra_installed, require_extra
from rangeret.io.regular_files import open_regular
from rangeret.models.weights.registry import PublishedModel, lookup, profile_for_published

if TYPE_CHECKING:  # torch is imported when weights are read, not to resolve their name
    from rangeret.models.network import RangeRet
    from rangeret.models.weights.checkpoint import CheckpointContent

#: The resolution of a published file, which records none, unless one is asked for.
DEFAULT_RESOLUTION = (64, 1024)

log = logging.getLogger(__name__)


class WeightsError(ModelError, RuntimeError):
    """Published weights that cannot be had: the hub unreachable, the file wrong or missing."""


def weights_url(model: PublishedModel) -> str:
    """The file's download URL on the hub `HF_ENDPOINT` names (by default huggingface.co)."""
    from huggingface_hub import hf_hub_url

    return hf_hub_url(model.repo, model.file, revision=model.revision)


def cached_weights(model: PublishedModel) -> Path | None:
    """The model's file in the local hub cache, or None when it was never downloaded (or the hub
    extra, which reads that cache, is not installed)."""
    if not extra_installed("hub"):
        return None
    from huggingface_hub import try_to_load_from_cache

    found = try_to_load_from_cache(model.repo, model.file, revision=model.revision)
    return Path(found) if isinstance(found, str) else None


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file, read in chunks."""
    digest = hashlib.sha256()
    with open_regular(path, "a weights file") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def fetch_weights(model: PublishedModel, to: Path | None = None) -> Path:
    """The model's file: from the cache when it is there (no network), else downloaded, into the
    hub cache or, with `to`, into that folder; checked against the registry's SHA-256 pin."""
    path = locate_weights(model, to)
    check_pin(model, path, file_sha256(path))
    return path


def locate_weights(model: PublishedModel, to: Path | None = None) -> Path:
    """The model's file from the cache, else downloaded (as `fetch_weights`), not read: a loader
    reads it once and checks the pin on the bytes it loads (`check_pin`)."""
    path = None if to is not None else cached_weights(model)
    if path is None:
        return _download(model, to)
    log.info("%s: in the local cache at %s", model.name, path)
    return path


def check_pin(model: PublishedModel, path: Path, sha256: str) -> None:
    """`WeightsError` (the file removed) when `sha256`, the hash of the file's bytes, is not the
    registry's pin for the model."""
    if model.sha256 is None:
        _note_unpinned(model, path, sha256)
    elif sha256 != model.sha256:
        _remove(path)
        raise WeightsError(
            f"the file downloaded for {model.name} has SHA-256 {sha256}, but the registry pins "
            f"{model.sha256}: it is not the published file, so it was removed; check the hub at "
            f"{weights_url(model)}"
        )
    log.info("%s: %s (sha256 %s)", model.name, path, sha256)


#: The unpinned models whose hash this process has logged already.
_NOTED: set[str] = set()


def _note_unpinned(model: PublishedModel, path: Path, sha256: str) -> None:
    """Log, once per model and process, the SHA-256 and size of a file the registry does not pin,
    so that a user can pin it in a registry of their own."""
    if model.name in _NOTED:
        return
    _NOTED.add(model.name)
    log.warning(
        "%s is not pinned in the registry: its file %s has sha256 %s and %d bytes; pin them "
        "(sha256:, size:) in your own registry (RANGERET_REGISTRY) to have them checked",
        model.name,
        path,
        sha256,
        path.stat().st_size,
    )


def _download(model: PublishedModel, to: Path | None) -> Path:
    """Download the file with a progress bar; `WeightsError` with one sentence when it fails,
    `MissingExtraError` without the hub extra."""
    require_extra(f"downloading {model.name}", "hub")
    from huggingface_hub import hf_hub_download

    url = weights_url(model)
    if _offline():
        raise WeightsError(_by_hand(model, url, "HF_HUB_OFFLINE is set and it is not in the cache"))
    log.info("%s: downloading %s", model.name, url)
    # The hub library logs each failed attempt; the one sentence below says it all.
    logging.getLogger("huggingface_hub.utils._http").setLevel(logging.ERROR)
    try:
        found = hf_hub_download(
            model.repo,
            model.file,
            revision=model.revision,
            local_dir=str(to) if to is not None else None,
        )
    except Exception as exc:  # the hub's, httpx's and the OS's errors all end the same way
        raise WeightsError(_by_hand(model, url, _reason(exc))) from exc
    return Path(found)


def _offline() -> bool:
    """Whether `HF_HUB_OFFLINE` forbids the network, read as huggingface_hub reads it."""
    from huggingface_hub import constants

    return bool(constants.HF_HUB_OFFLINE)


def _by_hand(model: PublishedModel, url: str, reason: str) -> str:
    """The sentence for weights that could not be downloaded: why, and what to do instead."""
    return (
        f"cannot get {model.name} from {url} ({reason}); download that file where the hub is "
        f"reachable and pass --checkpoint /path/to/{model.file}, or copy the hub cache "
        "(HF_HOME) of a machine that ran `rangeret weights download "
        f"{model.name}`"
    )


def _reason(exc: BaseException) -> str:
    """A short reason for a failed download: the HTTP status the hub answered, else the first
    line of the error at the root of the chain (the hub library wraps connection errors)."""
    chain = [exc]
    while (cause := chain[-1].__cause__ or chain[-1].__context__) is not None and len(chain) < 10:
        chain.append(cause)
    for error in chain:
        status = getattr(getattr(error, "response", None), "status_code", None)
        if status is not None:
            return f"the hub answered HTTP {status}"
    root = chain[-1]
    text = " ".join(str(root).split()) or type(root).__name__
    return text[:200]


def _remove(path: Path) -> None:
    """Delete a refused file, and the cache blob a cache link points to."""
    target = path.resolve()
    for p in {path, target}:
        with contextlib.suppress(FileNotFoundError):
            os.remove(p)


def published_name(value: str | Path) -> PublishedModel | None:
    """The registered model a `--checkpoint` value names (`rangeret-kitti-657`, or the file name
    `rangeret-kitti-657.pt` when no such file exists here), or None for a path."""
    text = str(value)
    if Path(text).exists() or os.sep in text:
        return None
    return lookup(text) or lookup(text.removesuffix(".pt"))


class CheckpointChanged(ModelError, RuntimeError):
    """A checkpoint file whose bytes are not those checked before (replaced, truncated)."""


@dataclass(frozen=True)
class ResolvedWeights:
    """Where a `--checkpoint` value leads, and the profile, network and resolution to load it
    with (what was asked for, completed by a published model's registry entry, whose pin the
    loaded bytes must match): the one path from a resolved name to its checkpoint's content
    (`checkpoint`) or its network (`network`), the file read once either way."""

    path: Path
    profile: DatasetProfile | None
    model: str | None
    height: int | None
    width: int | None
    published: PublishedModel | None = None
    #: The SHA-256 the bytes must have (a server reading again a file it checked at start).
    expected_sha256: str | None = None

    def read(self) -> tuple[bytes, str]:
        """The file's bytes, read once, and their SHA-256, checked against a published model's
        pin (`check_pin`) and `expected_sha256` on those very bytes, before they are parsed."""
        from rangeret.models.weights.checkpoint import read_checkpoint_bytes

        data = read_checkpoint_bytes(self.path)
        sha256 = hashlib.sha256(data).hexdigest()
        if self.published is not None:
            check_pin(self.published, self.path, sha256)
        if self.expected_sha256 is not None and sha256 != self.expected_sha256:
            raise CheckpointChanged(
                f"{self.path} is now {len(data):,} bytes of sha256 {sha256[:16]}, not the "
                f"checkpoint of sha256 {self.expected_sha256[:16]} read"
            )
        return data, sha256

    def checkpoint(
        self,
        *,
        default_resolution: tuple[int, int] = DEFAULT_RESOLUTION,
        overrides: Mapping[str, Any] | None = None,
    ) -> CheckpointContent:
        """The file's network configuration, tensors and records, its bytes read once (`read`),
        no network built. A published file runs at `default_resolution` unless a height or width
        was given; `overrides` are the switches a published file's tensors cannot tell, applied
        once its network is recognised (the project's own files record theirs)."""
        from rangeret.models.weights.checkpoint import checkpoint_from_bytes

        data, sha256 = self.read()
        shape = dict(height=self.height, width=self.width, default_resolution=default_resolution)
        content = checkpoint_from_bytes(data, self.path, self.model, sha256=sha256, **shape)
        if content.info.published and overrides:
            content = checkpoint_from_bytes(
                data, self.path, content.config.name, sha256=sha256, **shape, **overrides
            )
        return content

    def network(self, *, default_resolution: tuple[int, int] = DEFAULT_RESOLUTION) -> RangeRet:
        """The file's network in eval mode with its `checkpoint_info`, built from one read of
        its bytes (`checkpoint`)."""
        from rangeret.models.weights.checkpoint import network_of

        return network_of(self.checkpoint(default_resolution=default_resolution))


def resolve_weights(
    value: str | Path,
    profile: DatasetProfile | None = None,
    model: str | None = None,
    height: int | None = None,
    width: int | None = None,
) -> ResolvedWeights:
    """The file a `--checkpoint` value leads to, not read yet: a path as it is; for a published
    model's name its file (from the cache or the hub), with its profile (another requested one is
    refused before any download), network and resolution wherever those were not given."""
    published = published_name(value)
    if published is None:
        return ResolvedWeights(Path(value), profile, model, height, width)
    profile = profile_for_published(published, profile)
    return ResolvedWeights(
        locate_weights(published),
        profile,
        model or published.model,
        height or published.height or None,
        width or published.width or None,
        published,
    )
