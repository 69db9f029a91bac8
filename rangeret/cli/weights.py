"""`rangeret weights`: list the published models, or download one."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.commands import CommandError
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


def run(args: argparse.Namespace) -> int:
    """List the published models, or download one into the hub cache or a folder."""
    from rangeret.models.weights.hub import cached_weights, fetch_weights
    from rangeret.models.weights.registry import load_registry, lookup

    if args.action == "download":
        model = lookup(args.name)
        if model is None:
            known = ", ".join(sorted(load_registry()))
            raise CommandError(f"there is no published model {args.name!r}; known: {known}")
        path = fetch_weights(model, args.to)
        print(f"{model.name}: {path}")
        return 0
    rows = [("name", "dataset", "profile", "mIoU (%)", "cached", "size")]
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
                f"{size / 2**20:.1f} MiB" if size else "unknown",
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print(
            "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        )
    return 0


COMMAND = Subcommand("weights", "published models: list them, download one", add_arguments, run)
