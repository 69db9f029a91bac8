"""YAML read within bounds: the files a user hands in (profiles, label configurations, the model
registry) are parsed with PyYAML's safe loader, but a file larger than `MAX_BYTES`, nested deeper
than `MAX_DEPTH`, or whose aliases expand to more than `MAX_VALUES` values (a "billion laughs"
file) is refused in one short sentence before it can take memory or time.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from rangeret.exceptions import ConfigError
from rangeret.io.regular_files import FileTooLargeError, NotRegularFileError, read_regular

#: The largest YAML file read (the built-in profiles are a few KB).
MAX_BYTES = 1 << 20
#: The deepest nesting of mappings and sequences.
MAX_DEPTH = 64
#: The most values the document may hold once its aliases are expanded.
MAX_VALUES = 1_000_000


class YamlLimitError(ConfigError, ValueError):
    """A YAML file over one of the bounds, or not valid YAML; the message is one short line."""


class _BoundedLoader(yaml.SafeLoader):
    """The safe loader, counting depth and the expanded size of every node as it composes."""

    def __init__(self, stream: str, source: str) -> None:
        super().__init__(stream)
        self.source = source
        self.depth = 0
        self.sizes: dict[int, int] = {}

    def compose_node(self, parent, index):  # type: ignore[no-untyped-def]
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise YamlLimitError(f"{self.source} nests deeper than {MAX_DEPTH} levels")
        try:
            node = super().compose_node(parent, index)
        finally:
            self.depth -= 1
        size = self.sizes.get(id(node))
        if size is None:
            size = 1 + sum(self.sizes.get(id(child), 1) for child in _children(node))
            self.sizes[id(node)] = size
        if size > MAX_VALUES:
            raise YamlLimitError(
                f"{self.source} expands to more than {MAX_VALUES:,} values through its aliases"
            )
        return node


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [part for pair in node.value for part in pair]
    return []


def load_yaml_text(text: str, source: str) -> object:
    """The document in `text` (named `source` in errors), within the bounds; `YamlLimitError`
    naming `source` and the problem in one line otherwise."""
    if len(text.encode("utf-8", "replace")) > MAX_BYTES:
        raise YamlLimitError(f"{source} is larger than {MAX_BYTES:,} bytes")
    loader = _BoundedLoader(text, source)
    try:
        return loader.get_single_data()
    except yaml.YAMLError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise YamlLimitError(f"{source} is not valid YAML: {first[:200]}") from exc
    except RecursionError as exc:
        raise YamlLimitError(f"{source} nests too deeply") from exc
    finally:
        loader.dispose()


def load_yaml(path: Path | str) -> object:
    """The YAML file at `path`, within the bounds; `OSError` when it cannot be read,
    `YamlLimitError` when it is too large, too deep, too expanded or not YAML."""
    path = Path(path)
    try:
        data = read_regular(path, "a YAML file", MAX_BYTES)
    except (NotRegularFileError, FileTooLargeError) as exc:
        raise YamlLimitError(str(exc)) from None
    return load_yaml_text(data.decode("utf-8"), str(path))


def read_yaml(path: Path | str, what: str, error: type[Exception]) -> object:
    """The YAML file at `path` (`load_yaml`) as `what` (e.g. "the profile"), or `error`: "cannot
    read WHAT PATH: ..." for a file that cannot be read, the bound it passes for one too large."""
    try:
        return load_yaml(path)
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read {what} {path}: {exc}") from exc
    except YamlLimitError as exc:
        raise error(str(exc)) from exc
