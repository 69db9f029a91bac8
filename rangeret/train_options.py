"""The options of `rangeret train` and `python -m workers.train_job`, derived from `TrainConfig`.

`add_dataclass_options` turns a dataclass whose fields carry `rangeret.training.config.setting`
metadata into argparse options (type, choices, default and help written once, on the field);
`add_training_options` adds those of `TrainConfig` with `--config`, `--print-config` and
`--no-amp`; and `config_from_args` turns the parsed options, over the `--config` file's settings,
into a `TrainConfig`. Options left off the command line are None here, so a file's value stands
unless the command line gives another. With `--init-from` the checkpoint's network settles
`--model` and `--override`, which may then only repeat it.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from pathlib import Path
from typing import Any

from rangeret.inference.network_fields import option_help
from rangeret.training.config import TrainConfig, TrainConfigError
from rangeret.training.config_file import (
    field_choices,
    read_config_file,
    split_optional,
)


def option_flag(f: dataclasses.Field) -> str | None:
    """The command-line flag of a field: its `flag` metadata, else --field-name (None: none)."""
    return f.metadata.get("flag", "--" + f.name.replace("_", "-"))


def add_dataclass_options(
    parser: argparse.ArgumentParser, cls: type
) -> dict[str, argparse._ArgumentGroup]:
    """Add an option for every field of `cls` that has a flag, in argument groups named by the
    fields' `group` (returned by name); each option's default is None, meaning not given."""
    hints = typing.get_type_hints(cls)
    groups: dict[str, argparse._ArgumentGroup] = {}
    for f in dataclasses.fields(cls):
        flag = option_flag(f)
        if "help" not in f.metadata or flag is None:
            continue
        meta = f.metadata
        kind, _ = split_optional(hints[f.name])
        options: dict[str, Any] = {"dest": f.name, "default": None, "help": option_help(f)}
        if kind is bool:
            options["action"] = "store_true"
        elif "parse" in meta:
            options["action"] = "append"
        elif typing.get_origin(kind) is tuple:
            options["nargs"] = meta.get("nargs", "+")
            options["type"] = typing.get_args(kind)[0]
        else:
            options["type"] = kind
        choices = field_choices(f)
        if choices is not None:
            options["choices"] = list(choices)
        if "metavar" in meta:
            options["metavar"] = meta["metavar"]
        group = groups.get(meta["group"]) or parser.add_argument_group(meta["group"])
        groups[meta["group"]] = group
        group.add_argument(flag, **options)
    return groups


def add_training_options(parser: argparse.ArgumentParser) -> None:
    """The options that define a training run (everything but where it runs): `--config`,
    `--print-config`, one option per `TrainConfig` field and `--no-amp`."""
    parser.add_argument(
        "--config",
        type=Path,
        metavar="FILE.yaml",
        help="training settings as YAML, by field name (as --print-config writes them); "
        "options given on the command line take precedence",
    )
    parser.add_argument(
        "--print-config",
        action="store_true",
        help="write the resolved settings as YAML to stdout (for --config) and exit",
    )
    groups = add_dataclass_options(parser, TrainConfig)
    groups["optimisation"].add_argument(
        "--no-amp",
        action="store_true",
        help="the same as --precision fp32 (no mixed precision), kept for older command lines",
    )


def given_settings(args: argparse.Namespace, cls: type = TrainConfig) -> dict[str, Any]:
    """The fields of `cls` given on the command line, in the fields' types (`negate` flags turn
    their field off, `parse` options give name-value pairs)."""
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        value = getattr(args, f.name, None)
        if option_flag(f) is None or value is None:
            continue
        if f.metadata.get("negate"):
            value = not value
        elif "parse" in f.metadata:
            value = tuple(f.metadata["parse"](item) for item in value)
        elif isinstance(value, list):
            value = tuple(value)
        values[f.name] = value
    return values


def precision_from_args(args: argparse.Namespace, configured: str | None) -> str | None:
    """--precision over the `configured` one, with --no-amp read as fp32; a --precision that
    contradicts --no-amp is a ValueError naming both."""
    given = getattr(args, "precision", None)
    if not getattr(args, "no_amp", False):
        return given if given is not None else configured
    if given not in (None, "auto", "fp32"):
        raise TrainConfigError(
            f"--no-amp means --precision fp32 and contradicts --precision {given}: give one of them"
        )
    return "fp32"


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The `TrainConfig` of parsed training options over the settings of their `--config` file
    (ValueError on invalid values); paths are made absolute, so that workers in other folders
    and resumed runs read the same ones, and an `--init-from` checkpoint's network fills in the
    model and its overrides (those given must repeat it)."""
    source = getattr(args, "config", None)
    values = read_config_file(source) if source is not None else {}
    for name, value in given_settings(args).items():
        if "parse" in TrainConfig.__dataclass_fields__[name].metadata:
            value = tuple({**dict(values.get(name, ())), **dict(value)}.items())
        values[name] = value
    precision = precision_from_args(args, values.get("precision"))
    if precision is not None:
        values["precision"] = precision
    if getattr(args, "quiet", False):
        values["progress"] = False
    fields = dataclasses.fields(TrainConfig)
    for f in fields:
        if values.get(f.name) is not None and "resolve" in f.metadata:
            values[f.name] = f.metadata["resolve"](values[f.name])
    missing = [
        f
        for f in fields
        if f.metadata.get("required")
        and f.name not in values
        and values.get(f.metadata.get("settled_by", "")) is None
    ]
    if missing:
        raise TrainConfigError(
            f"the following settings are required: {', '.join(option_flag(f) for f in missing)}"
            + (f" (on the command line or in {source})" if source else " (or give --config FILE)")
        )
    if values.get("init_from") is not None:
        from rangeret.training.init_from import read_parent, settle_network

        overrides = dict(values.get("model_overrides", ()))
        parent = read_parent(values["init_from"], overrides)
        values.update(settle_network(parent, values.get("model"), overrides))
    return TrainConfig(**values)
