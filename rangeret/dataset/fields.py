"""Reading a configuration's fields with errors of one shape: `SOURCE: FIELD.PATH: PROBLEM`.

Profiles and label configurations are plain data (YAML or JSON); every check of a field goes
through `Fields`, so each message names its file (or "checkpoint X", "profile Y") and the field.
`is_int` and `is_number` are the project's one test of a plain value that must be an integer or a
number and not a bool, wherever such a value is read (files, JSON, arguments, options).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from numbers import Integral, Real
from typing import Any, NoReturn

from rangeret.exceptions import ConfigError


def is_int(value: Any) -> bool:
    """An integer (a numpy one too) that is not a bool: YAML's and JSON's true is an int to
    Python, but never a count, a size or an id; every check of an integer value asks this."""
    return isinstance(value, Integral) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """A real number (an integer too) that is not a bool; every check of a number asks this."""
    return isinstance(value, Real) and not isinstance(value, bool)


class Fields:
    """One mapping of a configuration being read, that names the field path in every error.

    `error` is the ConfigError raised (`ProfileError`, `LabelConfigError`); `kind` names the
    configuration in the message about an unexpected field ("a profile field").
    """

    def __init__(
        self,
        data: Any,
        source: str,
        path: str = "",
        *,
        error: type[ConfigError],
        kind: str = "field",
    ) -> None:
        self.source, self.path, self.error, self.kind = source, path, error, kind
        if not isinstance(data, Mapping):
            where = f"{path}: " if path else ""
            raise error(f"{source}: {where}must be a mapping of fields, got {type(data).__name__}")
        self.data = data

    def name(self, key: str) -> str:
        """The dotted path of `key` in this mapping."""
        return f"{self.path}.{key}" if self.path else key

    def fail(self, key: str, problem: str) -> NoReturn:
        """Raise the error naming `key`; an empty key names this mapping itself."""
        where = self.name(key) if key else self.path
        raise self.error(
            f"{self.source}: {where}: {problem}" if where else f"{self.source}: {problem}"
        )

    def child(self, key: str, data: Any) -> Fields:
        """The mapping `data`, found at `key` of this one."""
        return Fields(data, self.source, self.name(key), error=self.error, kind=self.kind)

    def finish(self, keys: Sequence[str], optional: Sequence[str] = ()) -> None:
        """Every expected field is there (the `optional` ones may be absent), and no other."""
        known = (*keys, *optional)
        extra = sorted(str(k) for k in self.data if k not in known)
        if extra:
            self.fail(extra[0], f"is not a {self.kind} (expected: {', '.join(known)})")
        self.require(keys)

    def require(self, keys: Sequence[str]) -> None:
        """Every one of `keys` is there."""
        missing = [k for k in keys if k not in self.data]
        if missing:
            self.fail(missing[0], "is missing")

    def get(self, key: str, kind: type | tuple[type, ...]) -> Any:
        """The value of a field that must be there and of `kind`."""
        if key not in self.data:
            self.fail(key, "is missing")
        value = self.data[key]
        if not isinstance(value, kind):
            name = (
                kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
            )
            self.fail(key, f"must be a {name}, got {value!r}")
        return value

    def section(self, key: str, keys: Sequence[str], optional: Sequence[str] = ()) -> Fields:
        """The mapping at `key`, holding exactly `keys` (and maybe the `optional` ones)."""
        if key not in self.data:
            self.fail(key, "is missing")
        section = self.child(key, self.data[key])
        section.finish(keys, optional)
        return section

    def mapping(self, key: str) -> Fields:
        """The mapping at `key`, whatever it holds."""
        if key not in self.data:
            self.fail(key, "is missing")
        return self.child(key, self.data[key])

    def integer(self, key: str, low: int, high: int | None = None) -> int:
        """An integer field within low..high."""
        value = self.data[key]
        if not is_int(value) or value < low or (high is not None and value > high):
            bound = f"{low}..{high}" if high is not None else f"at least {low}"
            self.fail(key, f"must be an integer {bound}, got {value!r}")
        return value

    def number(self, key: str) -> float:
        """A number field."""
        value = self.data[key]
        if not is_number(value):
            self.fail(key, f"must be a number, got {value!r}")
        return float(value)

    def numbers(self, key: str, count: int) -> tuple[float, ...]:
        """A field holding a list of exactly `count` numbers."""
        value = self.data[key]
        if not isinstance(value, list) or len(value) != count or not all(map(is_number, value)):
            self.fail(key, f"must be a list of {count} numbers, got {value!r}")
        return tuple(float(v) for v in value)

    def strings(self, key: str) -> list[str]:
        """A field holding a list of names."""
        value = self.data[key]
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            self.fail(key, f"must be a list of names, got {value!r}")
        return value

    def choice(self, key: str, choices: Sequence[str]) -> str:
        """A field holding one of `choices`."""
        value = self.data[key]
        if value not in choices:
            self.fail(key, f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    def records(
        self, key: str, keys: Sequence[str], optional: Sequence[str] = ()
    ) -> list[dict[str, Any]]:
        """A field holding a list of mappings, each with exactly `keys` (and maybe `optional`)."""
        if key not in self.data:
            self.fail(key, "is missing")
        value = self.data[key]
        if not isinstance(value, list):
            self.fail(key, f"must be a list, got {value!r}")
        for i, item in enumerate(value):
            self.child(f"{key}[{i}]", item).finish(keys, optional)
        return value
