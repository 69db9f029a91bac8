"""Reading and writing networks' checkpoints.

Two kinds of file load:

- published: a bare state_dict, or a dict holding one under `model_state_dict` (how the released
  `rangeret-kitti-657.pt` comes). The network is recognised from its keys (`rem.conv_block.*` is
  `rangeret-cir`, `rem.blocks.*` `rangeret-thesis`), its number of blocks counted from them, its
  classes, width and patch size read from the shapes. Such files do not record the resolution:
  it comes from the caller (64 x 1024 by default).
- the project's own, written by `save_checkpoint`: a dict of plain python values and tensors
  (`format`, `format_version`, `model`, `config`, `state_dict`, `label_config`, `projection`,
  `metadata`, and since profiles exist `profile`) that `load_checkpoint(path)` rebuilds with
  nothing else.

Every file is read with `torch.load(weights_only=True)` and loaded strictly: missing, unexpected
or mis-shaped keys raise `CheckpointError` naming them. The returned module is in eval mode and
carries a `CheckpointInfo` as `model.checkpoint_info`. `checkpoint_from_bytes` reads a file the
same way without loading it into a network, for callers that match its tensors against another
one (`rangeret train --init-from`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rangeret.exceptions import ModelError
from rangeret.io.atomic import atomic_write_bytes
from rangeret.io.regular_files import NotRegularFileError, read_regular
from rangeret.models.configs import OVERRIDES, ModelConfig, list_models, resolve_config
from rangeret.models.network import RangeRet
from rangeret.models.weights.checkpoint_info import CheckpointInfo

FORMAT = "rangeret-checkpoint"
FORMAT_VERSION = 1

_LISTED = 8


class CheckpointError(ModelError, ValueError):
    """A file that is not a loadable RangeRet checkpoint, or does not fit the network asked for."""


def save_checkpoint(
    path: str | os.PathLike[str],
    model: RangeRet,
    *,
    label_config: Any = None,
    projection: Any = None,
    metadata: Any = None,
    profile: Any = None,
) -> str:
    """Write `model` with its configuration and the given plain-data records; return the SHA-256.

    label_config, projection, metadata and profile are dicts (or dataclasses, or objects with
    `to_dict()`) of plain values; the file is written atomically and loads with `weights_only=True`.
    """
    if not isinstance(model, RangeRet):
        raise TypeError(f"save_checkpoint takes a RangeRet network, got {type(model).__name__}")
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model": model.config.name,
        "config": model.config.to_dict(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "label_config": _plain_record(label_config, "label_config"),
        "projection": _plain_record(projection, "projection"),
        "metadata": _plain_record(metadata, "metadata"),
        "profile": _plain_record(profile, "profile"),
    }
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    data = buffer.getvalue()
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def load_checkpoint(
    path: str | os.PathLike[str],
    model: str | None = None,
    height: int | None = None,
    width: int | None = None,
    **overrides: Any,
) -> RangeRet:
    """The network stored in `path`, in eval mode, with `checkpoint_info` attached: its bytes
    read once, then `network_from_bytes` (`default_resolution` and the switches as there)."""
    return network_from_bytes(read_checkpoint_bytes(path), path, model, height, width, **overrides)


def read_checkpoint_bytes(path: str | os.PathLike[str]) -> bytes:
    """The bytes of a checkpoint file, read once (`InputFileMissing` when it is not there); a
    folder, FIFO or device is a `CheckpointError` naming its kind, before a byte is read."""
    try:
        return read_regular(path, "a checkpoint")
    except NotRegularFileError as exc:
        raise CheckpointError(str(exc)) from None


def network_from_bytes(
    data: bytes,
    path: str | os.PathLike[str],
    model: str | None = None,
    height: int | None = None,
    width: int | None = None,
    *,
    default_resolution: tuple[int, int] = (64, 1024),
    sha256: str | None = None,
    **overrides: Any,
) -> RangeRet:
    """The network of a checkpoint file's bytes `data` (read from `path`, which errors and the
    `checkpoint_info` name), in eval mode; `sha256` is the bytes' hash when the caller has it.

    For published files `model` overrides the recognised name, height/width give the resolution
    (default `default_resolution`, a dataset profile's) and overrides the switches. For the
    project's own files everything comes from the file; arguments that contradict it raise
    CheckpointError.
    """
    content = checkpoint_from_bytes(
        data,
        path,
        model,
        height,
        width,
        default_resolution=default_resolution,
        sha256=sha256,
        **overrides,
    )
    return network_of(content)


def network_of(content: CheckpointContent) -> RangeRet:
    """The network a checkpoint's content describes, its tensors loaded strictly (`CheckpointError`
    naming every wrong key), in eval mode, with its `checkpoint_info`."""
    network = RangeRet(content.config)
    _check_keys(Path(content.info.path), network, content.state_dict, content.info.published)
    network.load_state_dict(content.state_dict, strict=True)
    network.eval()
    network.checkpoint_info = content.info
    return network


@dataclasses.dataclass(frozen=True)
class CheckpointContent:
    """What a checkpoint file holds, not yet loaded into a network: the configuration of its
    network, its tensors by name, and its `CheckpointInfo`."""

    config: ModelConfig
    state_dict: Mapping[str, torch.Tensor]
    info: CheckpointInfo


def _load_reason(exc: BaseException) -> str:
    """Why torch.load refused a file, in a few words: its unpickler's own line where it gave one,
    never torch's advice to load the file without `weights_only`."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for line in lines:
        if line.startswith("WeightsUnpickler error:"):
            return line.removeprefix("WeightsUnpickler error:").strip().rstrip(".")
    if not lines or "weights_only" in lines[0]:
        return "it is no file of tensors and plain data"
    return lines[0].rstrip(".")


def checkpoint_from_bytes(
    data: bytes,
    path: str | os.PathLike[str],
    model: str | None = None,
    height: int | None = None,
    width: int | None = None,
    *,
    default_resolution: tuple[int, int] = (64, 1024),
    sha256: str | None = None,
    **overrides: Any,
) -> CheckpointContent:
    """The configuration, tensors and records of a checkpoint file's bytes, read as
    `network_from_bytes` reads them but not loaded into a network, so that a caller can match
    the tensors against another network (fine-tuning with a new head)."""
    path = Path(path)
    digest = sha256 or hashlib.sha256(data).hexdigest()
    if path.suffix.lower() == ".onnx":
        raise CheckpointError(
            f"{path} is an ONNX export, not a checkpoint: pass the checkpoint it was exported from "
            "as --checkpoint, and the export as --onnx with --backend onnxruntime"
        )
    try:
        content = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:
        raise CheckpointError(
            f"{path} is not a RangeRet checkpoint: torch.load(weights_only=True) cannot read it "
            f"({_load_reason(exc)})"
        ) from exc

    if isinstance(content, Mapping) and content.get("format") == FORMAT:
        config, state = _own_config(path, content, model, height, width, overrides)
        records = {k: content.get(k) for k in ("label_config", "projection", "metadata", "profile")}
        published = False
    else:
        state = _published_state(path, content)
        resolution = (height or default_resolution[0], width or default_resolution[1])
        config = _published_config(path, state, model, resolution, overrides)
        records = {"label_config": None, "projection": None, "metadata": None, "profile": None}
        published = True

    info = CheckpointInfo(
        path=str(path),
        sha256=digest,
        name=config.name,
        config=config.to_dict(),
        published=published,
        **records,
    )
    return CheckpointContent(config, state, info)


def describe_state_dict(state: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """What the keys and shapes of a state_dict say about its network (None where they are silent)."""
    keys = list(state)
    if any(k.startswith("rem.conv_block.") for k in keys):
        name, rem = "rangeret-cir", "conv"
    elif any(k.startswith("rem.blocks.0.conv.") for k in keys):
        name, rem = "rangeret-thesis", "conv"
    elif any(k.startswith("rem.blocks.0.linear.") for k in keys):
        family_cir = any(".dwconv." in k for k in keys)
        name, rem = ("rangeret-cir" if family_cir else "rangeret-thesis"), "linear"
    else:
        name, rem = None, None
    blocks = {int(m.group(1)) for k in keys if (m := re.match(r"backbone\.retentions\.(\d+)\.", k))}
    info: dict[str, Any] = {
        "model": name,
        "rem": rem,
        "layers": max(blocks) + 1 if blocks else None,
    }
    head = state.get("head.mlp2.weight")
    info["num_classes"] = (
        int(head.shape[0]) if isinstance(head, torch.Tensor) and head.dim() == 2 else None
    )
    proj = state.get("viembed.proj.weight")
    valid_proj = isinstance(proj, torch.Tensor) and proj.dim() == 4
    info["dim"] = int(proj.shape[0]) if valid_proj else None
    info["patch_size"] = (int(proj.shape[2]), int(proj.shape[3])) if valid_proj else None
    if name == "rangeret-thesis" and blocks:
        info["mixer"] = (
            "retention" if "backbone.retentions.0.g_proj.weight" in state else "attention"
        )
    return info


def _own_config(
    path: Path,
    content: Mapping[str, Any],
    model: str | None,
    height: int | None,
    width: int | None,
    overrides: Mapping[str, Any],
) -> tuple[ModelConfig, Mapping[str, torch.Tensor]]:
    """Configuration and state_dict of a project checkpoint; requests that contradict it raise."""
    version = content.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format version {version!r}; this code reads {FORMAT_VERSION}"
        )
    try:
        recorded = ModelConfig.from_dict(content["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path} holds an invalid model configuration: {exc}") from exc
    state = content.get("state_dict")
    if not _is_state_dict(state):
        raise CheckpointError(f"{path} is a RangeRet checkpoint without a valid state_dict")
    unknown = sorted(set(overrides) - set(OVERRIDES))
    if unknown:
        raise CheckpointError(
            f"unknown overrides {', '.join(unknown)}; accepted: {', '.join(OVERRIDES)}"
        )
    conflicts = []
    if model is not None and model != recorded.name:
        conflicts.append(f"model {model!r} requested, {recorded.name!r} recorded")
    for field, value in (("height", height), ("width", width)):
        if value is not None and value != getattr(recorded, field):
            conflicts.append(f"{field} {value} requested, {getattr(recorded, field)} recorded")
    if overrides:
        try:
            wanted = resolve_config(
                recorded.name,
                recorded.height,
                recorded.width,
                recorded.num_classes,
                **{**recorded.overrides(), **overrides},
            )
        except ValueError as exc:
            raise CheckpointError(f"cannot apply overrides to {path}: {exc}") from exc
        conflicts += [
            f"{field} {getattr(wanted, field)!r} requested, {getattr(recorded, field)!r} recorded"
            for field in OVERRIDES
            if getattr(wanted, field) != getattr(recorded, field)
        ]
    if conflicts:
        raise CheckpointError(
            f"{path} records {_summary(recorded)} and loads only as recorded: "
            + "; ".join(conflicts)
            + ". Leave model, height, width and overrides unset to use the recorded configuration."
        )
    return recorded, state


def _published_state(path: Path, content: Any) -> Mapping[str, torch.Tensor]:
    """The state_dict of a published file: bare, or under `model_state_dict`."""
    if isinstance(content, Mapping) and "model_state_dict" in content:
        content = content["model_state_dict"]
    if not _is_state_dict(content):
        raise CheckpointError(
            f"{path} holds neither a state_dict (names to tensors), a dict with 'model_state_dict', "
            "nor a RangeRet checkpoint"
        )
    return content


def _published_config(
    path: Path,
    state: Mapping[str, torch.Tensor],
    model: str | None,
    resolution: tuple[int, int],
    overrides: Mapping[str, Any],
) -> ModelConfig:
    """The configuration a published state_dict is loaded into."""
    found = describe_state_dict(state)
    name = model or found["model"]
    if name is None:
        raise CheckpointError(
            f"{path} holds a state_dict whose keys fit neither network ({', '.join(list_models())}): "
            f"it has no rem.conv_block.* or rem.blocks.* keys; first keys: {', '.join(list(state)[:_LISTED])}"
        )
    inferred = {
        k: found[k]
        for k in ("layers", "dim", "patch_size", "rem", "mixer")
        if found.get(k) is not None
    }
    if name != found["model"]:
        inferred = {k: v for k, v in inferred.items() if k == "layers"}
    classes = found["num_classes"] or 20
    try:
        return resolve_config(
            name, resolution[0], resolution[1], classes, **{**inferred, **overrides}
        )
    except ValueError as exc:
        raise CheckpointError(
            f"cannot load {path} as {name} at {resolution[0]}x{resolution[1]}: {exc}"
        ) from exc


def _check_keys(
    path: Path, network: RangeRet, state: Mapping[str, torch.Tensor], published: bool
) -> None:
    """Raise CheckpointError naming every missing, unexpected or mis-shaped key."""
    expected = network.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    misshaped = [
        f"{k} {tuple(state[k].shape)} in the file, {tuple(v.shape)} in the network"
        for k, v in expected.items()
        if k in state and tuple(state[k].shape) != tuple(v.shape)
    ]
    if not (missing or unexpected or misshaped):
        return
    problems = [
        f"{label} ({len(items)}): {', '.join(items[:_LISTED])}{', ...' if len(items) > _LISTED else ''}"
        for label, items in (
            ("missing keys", missing),
            ("unexpected keys", unexpected),
            ("mis-shaped keys", misshaped),
        )
        if items
    ]
    found = describe_state_dict(state)
    fits = _describe_found(found, published)
    raise CheckpointError(
        f"{path} does not fit {_summary(network.config)}: " + "; ".join(problems) + f". {fits}"
    )


def _describe_found(found: Mapping[str, Any], published: bool) -> str:
    """One sentence on the network the keys describe."""
    if found["model"] is None:
        return "Its keys fit neither " + " nor ".join(list_models()) + "."
    parts = [f"{found['layers']} blocks" if found["layers"] else "no blocks"]
    if found["num_classes"]:
        parts.append(f"{found['num_classes']} classes")
    if found["dim"]:
        parts.append(f"width {found['dim']}")
    if found["patch_size"]:
        parts.append(f"{found['patch_size'][0]}x{found['patch_size'][1]} patches")
    if found["rem"] == "linear":
        parts.append("the linear REM")
    text = f"The file's keys fit {found['model']} with {', '.join(parts)}"
    if published:
        text += ", at any resolution (published files do not record it; pass height and width)"
    return text + "."


def _summary(config: ModelConfig) -> str:
    """'rangeret-cir at 64x1024 with 8 blocks and 20 classes'."""
    return (
        f"{config.name} at {config.height}x{config.width} with {config.layers} blocks "
        f"and {config.num_classes} classes"
    )


def _is_state_dict(value: Any) -> bool:
    """True for a non-empty mapping of names to tensors."""
    return (
        isinstance(value, Mapping)
        and len(value) > 0
        and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in value.items())
    )


def _plain_record(value: Any, name: str) -> dict[str, Any] | None:
    """`value` as a dict of plain python values and tensors, or TypeError naming what is not."""
    if value is None:
        return None
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    elif not isinstance(value, Mapping) and callable(getattr(value, "to_dict", None)):
        value = value.to_dict()
    if not isinstance(value, Mapping):
        raise TypeError(f"{name} must be a dict, got {type(value).__name__}")
    return _plain(value, name)


def _plain(value: Any, where: str) -> Any:
    """A copy of `value` with numpy values made python ones; TypeError for anything else not plain."""
    if value is None or isinstance(value, (bool, int, float, str, torch.Tensor)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, (str, int)):
                raise TypeError(
                    f"{where} has a key of type {type(k).__name__}; keys must be str or int"
                )
            out[k] = _plain(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise TypeError(
        f"{where} is a {type(value).__name__}; checkpoints store plain python values and tensors"
    )
