"""A `TrainConfig` as a YAML file: the settings `rangeret train --config FILE` reads and
`--print-config` writes.

The file is a mapping of `TrainConfig` field names to values (`config_yaml` writes every field;
a file may hold any subset). Each value is checked against its field's type and choices, and an
unknown key or a bad value is a `TrainConfigError` naming the key and the file, in one line. Numbers
written as 1e-3 (a string to YAML 1.1) are read as numbers; sequence ids are strings ('00').
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from rangeret.dataset.fields import is_int, is_number
from rangeret.inference.network_fields import KIND_NAMES
from rangeret.io.bounded_yaml import load_yaml
from rangeret.training.config import TrainConfig, TrainConfigError, override_pairs


@functools.cache
def _fields() -> dict[str, tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(TrainConfig)
    return {f.name: (f, hints[f.name]) for f in dataclasses.fields(TrainConfig)}


def field_choices(f: dataclasses.Field) -> tuple[Any, ...] | None:
    """The values a field (or each of its items) may take, from its `choices` metadata."""
    choices = f.metadata.get("choices")
    return None if choices is None else tuple(choices)


def split_optional(hint: Any) -> tuple[Any, bool]:
    """(the type, whether None is allowed) of an annotation such as `int | None`."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return args[0], len(args) < len(typing.get_args(hint))
    return hint, False


_PLURALS = {bool: "booleans", int: "integers", float: "numbers", str: "strings (quoted: '00')"}


def _scalar(kind: type, value: Any) -> Any:
    """`value` as `kind` (a number may come as its text, as YAML 1.1 reads 1e-3), or raise
    TypeError naming the kind: no bool for a number, ints are numbers."""
    if (kind is bool or kind is str) and isinstance(value, kind):
        return value
    if kind is int and is_int(value):
        return int(value)
    if kind is float and is_number(value):
        return float(value)
    if kind is float and isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            pass
    raise TypeError(KIND_NAMES[kind])


def check_setting(name: str, value: Any, source: str) -> Any:
    """The value of setting `name` from `source`, in the field's own type; a `TrainConfigError`
    naming the key and `source` when the key is unknown or the value has the wrong type or is
    not one of the field's choices."""
    fields = _fields()
    if name not in fields:
        close = difflib.get_close_matches(str(name), fields, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise TrainConfigError(f"unknown setting {name!r} in {source}{hint}")
    f, hint = fields[name]
    kind, optional = split_optional(hint)
    if value is None:
        if optional:
            return None
        raise TrainConfigError(f"setting {name} in {source} needs a value")
    choices = field_choices(f)
    try:
        if typing.get_origin(kind) is tuple and "keys" in f.metadata:
            return _mapping(value, f.metadata["keys"])
        if typing.get_origin(kind) is tuple:
            item = typing.get_args(kind)[0]
            if isinstance(value, str) or not isinstance(value, Sequence):
                raise TypeError(f"a list of {_PLURALS[item]}")
            try:
                items = tuple(_scalar(item, v) for v in value)
            except TypeError:
                raise TypeError(f"a list of {_PLURALS[item]}") from None
        else:
            items = (_scalar(kind, value),)
    except TypeError as exc:
        raise TrainConfigError(f"setting {name} in {source} must be {exc}, got {value!r}") from None
    bad = [v for v in items if choices is not None and v not in choices]
    if bad:
        raise TrainConfigError(
            f"setting {name} in {source} must be one of {', '.join(map(str, choices))}, "
            f"got {bad[0]!r}"
        )
    return items if typing.get_origin(kind) is tuple else items[0]


def _mapping(value: Any, keys: Sequence[str]) -> tuple[tuple[str, Any], ...]:
    """A mapping setting (the model overrides) as name-value pairs; TypeError when it is not a
    mapping of the known names."""
    if not isinstance(value, Mapping):
        raise TypeError(f"a mapping of {', '.join(keys)}")
    unknown = [k for k in value if k not in keys]
    if unknown:
        raise TypeError(f"a mapping of {', '.join(keys)} (not {unknown[0]!r})")
    return override_pairs(value)


def read_config_file(path: Path | str) -> dict[str, Any]:
    """The settings in the YAML file at `path`, each checked by `check_setting`; a file that
    cannot be read or is not a mapping is a `TrainConfigError` naming it."""
    try:
        data = load_yaml(path)
    except OSError as exc:
        raise TrainConfigError(
            f"cannot read the training configuration {path}: {exc.strerror or exc}"
        ) from exc
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise TrainConfigError(
            f"{path} must map setting names to values, got a {type(data).__name__}"
        )
    return {name: check_setting(name, value, str(path)) for name, value in data.items()}


def config_yaml(config: TrainConfig) -> str:
    """Every setting of `config` as YAML, which `read_config_file` reads back to `config`."""
    return yaml.safe_dump(config.to_dict(), sort_keys=False, default_flow_style=False)
