"""`rangeret weights`: list the published models, download one, or show what a checkpoint holds."""

from __future__ import annotations

import argparse
import errno
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rangeret.commands import CommandError
from rangeret.exceptions import InputFileMissing
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    actions.add_parser(
        "list", help="the published models: dataset, mIoU, whether cached here, and size"
    )
    download = actions.add_parser(
        "download",
        help="fetch a published model into the hub cache (HF_HOME) or a folder",
        description="Downloads go through huggingface_hub: HF_ENDPOINT, HF_HOME, HF_HUB_OFFLINE "
        "and HF_TOKEN apply.",
    )
    download.add_argument("name", metavar="NAME", help="a name of `rangeret weights list`")
    download.add_argument(
        "--to", type=Path, metavar="DIR", help="this folder instead of the hub cache"
    )
    info = actions.add_parser(
        "info",
        help="what a checkpoint holds: SHA-256, network, profile and classes, parent, training",
    )
    info.add_argument(
        "checkpoint", metavar="CHECKPOINT", help="a checkpoint file, or a published model's name"
    )


def run(args: argparse.Namespace) -> int:
    """List the published models, download one into the hub cache or a folder, or print what a
    checkpoint holds."""
    from rangeret.models.weights.hub import cached_weights, fetch_weights
    from rangeret.models.weights.registry import load_registry, lookup

    if args.action == "info":
        for name, value in checkpoint_facts(args.checkpoint):
            print(f"{name + ':':<10} {value}")
        return 0
    if args.action == "download":
        model = lookup(args.name)
        if model is None:
            known = ", ".join(sorted(load_registry()))
            raise CommandError(f"there is no published model {args.name!r}; known: {known}")
        path = fetch_weights(model, args.to)
        print(f"{model.name}: {path}")
        return 0
    rows = [("name", "dataset", "profile", "mIoU (%)", "cached", "size", "sha256")]
    for model in load_registry().values():
        cached = cached_weights(model)
        size = cached.stat().st_size if cached else model.size
        rows.append(
            (
                model.name,
                model.dataset,
                model.profile,
                model.miou_text(),
                "yes" if cached else "no",
                f"{size / 2**20:.1f} MiB" if size else "not pinned",
                model.sha256[:12] if model.sha256 else "not pinned",
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print(
            "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        )
    return 0


def checkpoint_facts(value: str) -> list[tuple[str, str]]:
    """The facts `rangeret weights info` prints of the checkpoint `value` names (a file or a
    published model's name), as (name, text) pairs; a file that is missing or not a checkpoint
    is a one-line error."""

    from rangeret.io.regular_files import require_regular
    from rangeret.models.weights.hub import resolve_weights
    from rangeret.models.weights.run_profile import profile_for_checkpoint

    resolved = resolve_weights(value)
    if not resolved.path.exists():
        raise InputFileMissing(
            errno.ENOENT, "no such checkpoint file or published model", str(resolved.path)
        )
    require_regular(resolved.path, "a checkpoint")
    info = resolved.network().checkpoint_info
    config = info.config
    facts = [
        ("path", str(Path(info.path).resolve())),
        ("sha256", info.sha256),
        ("format", "published state_dict" if info.published else "rangeret checkpoint"),
        ("network", info.name),
        ("config", " ".join(f"{k}={_text(v)}" for k, v in config.items() if k != "name")),
    ]
    classes = int(config["num_classes"])
    if info.published:
        registry = resolved.published
        facts.append(
            (
                "profile",
                f"{registry.profile} (the registry's entry {registry.name})"
                if registry is not None
                else "not recorded (published weights record none)",
            )
        )
        facts.append(("classes", f"{classes} (names not recorded)"))
    else:
        profile = profile_for_checkpoint(info, requested=None)
        names = ", ".join(profile.labels.class_names)
        facts.append(("profile", profile.name))
        facts.append(("classes", f"{classes}: {names}"))
    facts.append(("parent", _parent_text(info.parent)))
    facts.append(("training", _training_text(info.metadata)))
    return facts


def _text(value: Any) -> str:
    """A configuration value as the command line writes it (pairs as AxB, booleans lower-case)."""
    if isinstance(value, (list, tuple)) and len(value) == 2:
        return f"{value[0]}x{value[1]}"
    return str(value).lower() if isinstance(value, bool) else str(value)


def _parent_text(parent: Mapping[str, Any] | None) -> str:
    """The parent line: what the run was started from, its SHA-256, what was loaded and made new."""
    if not parent:
        return "none (trained from scratch, or published)"
    text = f"{parent.get('source')} (sha256 {parent.get('sha256')}"
    if parent.get("path") and parent.get("path") != parent.get("source"):
        text += f", file {parent['path']}"
    if parent.get("model"):
        text += f"; {parent['model']} with {parent.get('num_classes')} classes"
    if parent.get("profile"):
        text += f" for the {parent['profile']} profile"
    else:
        text += " for a profile it does not record (a published file)"
    if "loaded" in parent:
        new = ", ".join(parent.get("new") or []) or "none"
        text += f"; {parent['loaded']} tensors loaded, new: {new}"
    return text + ")"


def _training_text(metadata: Mapping[str, Any] | None) -> str:
    """The training line: epoch, step and the best epoch, as the checkpoint's metadata has them."""
    meta = metadata or {}
    if "step" not in meta:
        return "not recorded"
    done = "complete" if meta.get("epoch_complete") else "in progress"
    text = f"epoch {meta.get('epoch')} ({done}), step {meta['step']}"
    if meta.get("total_steps"):
        text += f" of {meta['total_steps']}"
    best = meta.get("best")
    if best:
        text += f"; best: epoch {best['epoch']}, {best['metric']} {best['value']:.4f}"
    return text


COMMAND = Subcommand(
    "weights",
    "published models: list them, download one; what a checkpoint holds",
    add_arguments,
    run,
)
