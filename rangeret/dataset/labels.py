"""The label configuration: raw label ids, training classes, colours and splits.

Every source of a configuration goes through one parser, `parse_label_config`, of the content as
plain data: the project's own JSON layout (`data/semantickitti.json`, also a profile's `labels`
section), the official `semantic-kitti.yaml` layout (keys `labels`, `learning_map`,
`learning_map_inv`, `learning_ignore`, `color_map`, `split`) and the form a checkpoint stores
(`LabelConfig.to_dict`). Reading a file is separate (`load_label_config`). Every problem is a
`LabelConfigError` shaped `SOURCE: FIELD: PROBLEM`, naming the file, "checkpoint X" or "profile
Y", and the field.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from rangeret import DATA_DIR
from rangeret.dataset.fields import Fields, is_int, is_number
from rangeret.exceptions import ConfigError

#: Raw labels are the low 16 bits of each uint32 in a `.label` file.
SEMANTIC_MASK = 0xFFFF

#: How a configuration built in code (not read from a source) is named in its errors.
_BUILT = "label configuration"


class LabelConfigError(ConfigError, ValueError):
    """A label configuration that cannot be used: unreadable, inconsistent, or without a split;
    the message is `SOURCE: FIELD: PROBLEM`."""


@dataclass(frozen=True)
class LabelConfig:
    """Maps between raw label ids and training classes, with names, colours and splits."""

    class_names: tuple[str, ...]
    class_raw_ids: tuple[int, ...]
    ignored: tuple[bool, ...]
    raw_names: dict[int, str]
    raw_to_class: dict[int, int]
    raw_bgr: dict[int, tuple[int, int, int]]
    raw_frequency: dict[int, float]
    splits: dict[str, tuple[str, ...]]
    unlabeled_class: int | None = None
    _lut: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.class_names) != len(self.class_raw_ids) or len(self.ignored) != len(
            self.class_names
        ):
            raise LabelConfigError(
                f"{_BUILT}: class_names: classes, raw ids and ignore flags differ in length"
            )
        if self.unlabeled_class is None:
            default = self.raw_to_class.get(0, self.ignored.index(True) if any(self.ignored) else 0)
            object.__setattr__(self, "unlabeled_class", default)
        if not 0 <= self.unlabeled_class < self.num_classes:
            raise LabelConfigError(
                f"{_BUILT}: unlabeled_class: the unlabeled class {self.unlabeled_class} is not a "
                "class"
            )
        lut = np.full(SEMANTIC_MASK + 1, self.unlabeled_class, dtype=np.uint8)
        for raw, cls in self.raw_to_class.items():
            if not 0 <= raw <= SEMANTIC_MASK:
                raise LabelConfigError(f"{_BUILT}: raw_to_class: {_not_raw_id(raw)}")
            if not 0 <= cls < self.num_classes:
                raise LabelConfigError(
                    f"{_BUILT}: raw_to_class: {_unknown_class(raw, cls, self.num_classes)}"
                )
            lut[raw] = cls
        object.__setattr__(self, "_lut", lut)

    @property
    def num_classes(self) -> int:
        """Number of training classes, the ignored ones included (20 for SemanticKITTI)."""
        return len(self.class_names)

    @property
    def evaluated_classes(self) -> list[int]:
        """Training classes that count in mIoU (all but the ignored ones)."""
        return [c for c in range(self.num_classes) if not self.ignored[c]]

    @property
    def raw_lut(self) -> np.ndarray:
        """(65536,) uint8 table from a 16-bit raw id to its training class; unknown ids give the
        unlabeled class (0 for SemanticKITTI, the class raw id 0 maps to in general)."""
        return self._lut

    @property
    def inverse_lut(self) -> np.ndarray:
        """(num_classes,) uint32 table from a training class back to its raw id."""
        return np.asarray(self.class_raw_ids, dtype=np.uint32)

    @property
    def valid_prediction_ids(self) -> frozenset[int]:
        """Raw ids a prediction may hold: those the inverse map can produce."""
        return frozenset(self.class_raw_ids)

    def to_class(self, raw: np.ndarray) -> np.ndarray:
        """Training classes (uint8) of raw labels; instance bits are dropped, unknown ids give the
        unlabeled class."""
        raw = np.asarray(raw)
        return self._lut[raw.astype(np.int64, copy=False) & SEMANTIC_MASK]

    def to_raw(self, classes: np.ndarray) -> np.ndarray:
        """Raw ids (uint32) of training classes."""
        return self.inverse_lut[np.asarray(classes)]

    def class_bgr(self) -> np.ndarray:
        """(num_classes, 3) uint8 BGR colour of each training class."""
        return np.array([self.raw_bgr[r] for r in self.class_raw_ids], dtype=np.uint8)

    def class_rgb(self) -> np.ndarray:
        """(num_classes, 3) uint8 RGB colour of each training class, for plots."""
        return self.class_bgr()[:, ::-1].copy()

    def class_frequencies(self) -> np.ndarray:
        """(num_classes,) share of points in each training class, summed over its raw ids."""
        freq = np.zeros(self.num_classes, dtype=np.float64)
        for raw, share in self.raw_frequency.items():
            freq[self.raw_to_class.get(raw, self.unlabeled_class)] += share
        return freq

    def split(self, name: str) -> tuple[str, ...]:
        """Sequence names (two digits) of a split such as "train", "valid" or "test"."""
        try:
            return self.splits[name]
        except KeyError:
            import difflib

            close = difflib.get_close_matches(name, list(self.splits), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]}?" if close else ""
            raise LabelConfigError(
                f"unknown split {name!r}: the splits are {', '.join(self.splits)}{hint}"
            ) from None

    def to_dict(self) -> dict:
        """Plain-data form (JSON-safe), as stored in checkpoints and reports."""
        return {
            "class_names": list(self.class_names),
            "class_raw_ids": list(self.class_raw_ids),
            "ignored": list(self.ignored),
            "raw_names": {str(k): v for k, v in self.raw_names.items()},
            "raw_to_class": {str(k): v for k, v in self.raw_to_class.items()},
            "raw_bgr": {str(k): list(v) for k, v in self.raw_bgr.items()},
            "raw_frequency": {str(k): v for k, v in self.raw_frequency.items()},
            "splits": {k: list(v) for k, v in self.splits.items()},
            "unlabeled_class": self.unlabeled_class,
        }


# --- parsing: one validator over one normal form ---------------------------------------------


@dataclass
class _Class:
    """One training class as a source gives it, with the field each value came from."""

    name: Any
    raw_id: Any
    ignored: Any
    where: str
    #: The field its raw id came from.
    raw_where: str


@dataclass
class _Raw:
    """One raw label as a source gives it, with the field each value came from."""

    id: Any
    name: Any
    cls: Any
    bgr: Any
    frequency: Any
    where: Mapping[str, str]


@dataclass
class _Content:
    """A configuration in one normal form, whatever its source's layout."""

    classes: list[_Class]
    raws: list[_Raw]
    splits: Mapping[str, Any]
    splits_field: Fields
    unlabeled: tuple[Any, str] | None
    #: The field that lists the classes, named when there are too few.
    classes_field: str


def parse_label_config(
    data: Any,
    source: str,
    *,
    field: str = "",
    splits: Mapping[str, Any] | None = None,
    normalise: Callable[[str | int], str] = str,
) -> LabelConfig:
    """The label configuration of plain data in any of its layouts (the project's JSON, which a
    profile's `labels` section also uses; the official YAML; the stored `to_dict` form).

    `source` names it in errors (a file, "checkpoint X", "profile Y"), `field` is where the data
    sits in it ("labels" in a profile); a profile gives its `splits` section separately, and
    `normalise` writes split ids as its layout does. Anything wrong is a `LabelConfigError`
    shaped `SOURCE: FIELD: PROBLEM`.
    """
    f = Fields(data, source, field, error=LabelConfigError)
    if splits is not None:
        split_fields = Fields(splits, source, "splits", error=LabelConfigError)
    else:
        split_fields = None
    if "learning_map" in f.data:
        content = _official(f, split_fields)
        normalise = _two_digits
    elif "class_names" in f.data:
        content = _stored(f, split_fields)
    else:
        content = _project(f, split_fields)
    return _build(f, content, normalise)


def load_label_config(path: Path | str) -> LabelConfig:
    """The label configuration in a file: .yaml/.yml in the official layout (read within the
    bounds of `rangeret.io.bounded_yaml`), else the project's JSON."""
    path = Path(path)
    try:
        if path.suffix in {".yaml", ".yml"}:
            from rangeret.io.bounded_yaml import load_yaml

            data = load_yaml(path)
        else:
            data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise LabelConfigError(f"{path}: cannot read the label configuration: {exc}") from exc
    return parse_label_config(data, str(path))


def _two_digits(name: str | int) -> str:
    return f"{int(name):02d}" if str(name).strip().isdigit() else str(name)


def _key(value: Any) -> Any:
    """A mapping key as an integer where it is one ("10" or 10), else as given."""
    if is_int(value):
        return value
    text = str(value).strip()
    return int(text) if text.isdigit() else value


def _project(f: Fields, splits: Fields | None) -> _Content:
    """The project's own layout: `classes` ({id?, name, raw_id, ignored}), `raw_labels`
    ({id, name, class, bgr, frequency?}), `unlabeled_class?` and `splits`."""
    listed = f.records("classes", ("name", "raw_id", "ignored"), optional=("id",))
    raw_items = f.records("raw_labels", ("id", "name", "class", "bgr"), optional=("frequency",))
    order = list(range(len(listed)))
    if any("id" in c for c in listed):
        ids = [c.get("id") for c in listed]
        if not all(is_int(i) for i in ids) or sorted(ids) != list(range(len(ids))):
            f.fail("classes", "training class ids must be 0..N-1 without gaps")
        order = sorted(order, key=lambda i: ids[i])
    classes = [
        _Class(
            listed[i]["name"],
            listed[i]["raw_id"],
            listed[i]["ignored"],
            f"classes[{i}]",
            f"classes[{i}].raw_id",
        )
        for i in order
    ]
    raws = [
        _Raw(
            r["id"],
            r["name"],
            r["class"],
            r["bgr"],
            r.get("frequency", 0.0),
            {k: f"raw_labels[{i}].{k}" for k in ("id", "name", "class", "bgr", "frequency")},
        )
        for i, r in enumerate(raw_items)
    ]
    unlabeled = (
        (f.data["unlabeled_class"], "unlabeled_class") if "unlabeled_class" in f.data else None
    )
    split_fields = splits or f.mapping("splits")
    return _Content(classes, raws, split_fields.data, split_fields, unlabeled, "classes")


def _official(f: Fields, splits: Fields | None) -> _Content:
    """The official `semantic-kitti.yaml` layout."""
    f.require(("labels", "learning_map", "learning_map_inv"))
    inv_fields = f.mapping("learning_map_inv")
    inv = {_key(k): v for k, v in inv_fields.data.items()}
    n = len(inv)
    if not all(map(is_int, inv)) or sorted(inv) != list(range(n)):
        f.fail("learning_map_inv", "must cover classes 0..N-1")
    names = f.mapping("labels").data
    ignore = (
        {_key(k): v for k, v in f.mapping("learning_ignore").data.items()}
        if ("learning_ignore" in f.data)
        else {0: True}
    )
    names_by_id = {_key(k): v for k, v in names.items()}
    classes = [
        _Class(
            names_by_id.get(_key(inv[c]), f"class-{c}"),
            _key(inv[c]),
            bool(ignore.get(c, False)),
            f"labels.{inv[c]}",
            f"learning_map_inv.{c}",
        )
        for c in range(n)
    ]
    colours = (
        {_key(k): v for k, v in f.mapping("color_map").data.items()}
        if ("color_map" in f.data)
        else {}
    )
    content = (
        {_key(k): v for k, v in f.mapping("content").data.items()} if ("content" in f.data) else {}
    )
    where = {
        "id": "learning_map",
        "name": "labels",
        "class": "learning_map",
        "bgr": "color_map",
        "frequency": "content",
    }
    raws = [
        _Raw(
            _key(k),
            str(names_by_id.get(_key(k), _key(k))),
            v,
            colours.get(_key(k), (0, 0, 0)),
            content.get(_key(k), 0.0),
            where,
        )
        for k, v in f.mapping("learning_map").data.items()
    ]
    split_fields = splits or (f.mapping("split") if "split" in f.data else f.child("split", {}))
    return _Content(classes, raws, split_fields.data, split_fields, None, "learning_map_inv")


def _stored(f: Fields, splits: Fields | None) -> _Content:
    """The stored form of `LabelConfig.to_dict` (checkpoints, reports)."""
    f.require(("class_names", "class_raw_ids", "ignored", "raw_to_class"))
    names, raw_ids, ignored = (f.get(k, list) for k in ("class_names", "class_raw_ids", "ignored"))
    if not len(names) == len(raw_ids) == len(ignored):
        f.fail("class_raw_ids", "classes, raw ids and ignore flags differ in length")
    classes = [
        _Class(
            names[c], _key(raw_ids[c]), bool(ignored[c]), f"class_names[{c}]", f"class_raw_ids[{c}]"
        )
        for c in range(len(names))
    ]
    extra = {k: f.data.get(k) or {} for k in ("raw_names", "raw_bgr", "raw_frequency")}
    by_id = {k: {_key(r): v for r, v in table.items()} for k, table in extra.items()}
    where = {
        "id": "raw_to_class",
        "name": "raw_names",
        "class": "raw_to_class",
        "bgr": "raw_bgr",
        "frequency": "raw_frequency",
    }
    raws = [
        _Raw(
            _key(k),
            by_id["raw_names"].get(_key(k), str(k)),
            v,
            by_id["raw_bgr"].get(_key(k), (0, 0, 0)),
            by_id["raw_frequency"].get(_key(k), 0.0),
            where,
        )
        for k, v in f.mapping("raw_to_class").data.items()
    ]
    unlabeled = f.data.get("unlabeled_class")
    split_fields = splits or (f.mapping("splits") if "splits" in f.data else f.child("splits", {}))
    return _Content(
        classes,
        raws,
        split_fields.data,
        split_fields,
        None if unlabeled is None else (unlabeled, "unlabeled_class"),
        "class_names",
    )


def _not_raw_id(raw: Any) -> str:
    return f"must be a raw id 0..{SEMANTIC_MASK}, got {raw!r}"


def _unknown_class(raw: Any, cls: Any, num_classes: int) -> str:
    return f"raw id {raw} maps to unknown class {cls!r} (must be a class 0..{num_classes - 1})"


def _build(f: Fields, content: _Content, normalise: Callable[[str | int], str]) -> LabelConfig:
    """The configuration of a normal form, every value checked once, whatever the source."""
    classes, n = content.classes, len(content.classes)
    if n < 2:
        f.fail(content.classes_field, f"must list at least 2 classes, got {n}")
    for c in classes:
        if not isinstance(c.name, str) or not isinstance(c.ignored, bool):
            f.fail(c.where, "needs a text name and a true/false ignored")
    raw_to_class: dict[int, int] = {}
    for r in content.raws:
        if not is_int(r.id) or not 0 <= r.id <= SEMANTIC_MASK:
            f.fail(r.where["id"], _not_raw_id(r.id))
        if not is_int(r.cls) or not 0 <= r.cls < n:
            f.fail(r.where["class"], _unknown_class(r.id, r.cls, n))
        if r.id in raw_to_class:
            f.fail(r.where["id"], f"raw id {r.id} is listed twice")
        bgr = list(r.bgr) if isinstance(r.bgr, list | tuple) else r.bgr
        if not (
            isinstance(bgr, list)
            and len(bgr) == 3
            and all(is_int(v) and 0 <= v <= 255 for v in bgr)
        ):
            f.fail(r.where["bgr"], f"raw id {r.id}: must be three integers 0..255, got {r.bgr!r}")
        if not is_number(r.frequency):
            f.fail(r.where["frequency"], f"raw id {r.id}: must be a number, got {r.frequency!r}")
        raw_to_class[r.id] = r.cls
    for i, c in enumerate(classes):
        if c.raw_id not in raw_to_class:
            f.fail(c.raw_where, f"raw id {c.raw_id!r} is not among the raw labels")
        if raw_to_class[c.raw_id] != i:
            f.fail(
                c.raw_where,
                f"raw id {c.raw_id} maps to class {raw_to_class[c.raw_id]}, not back to class {i}",
            )
    split_ids: dict[str, tuple[str, ...]] = {}
    for name, ids in content.splits.items():
        if not isinstance(ids, list | tuple) or not all(
            isinstance(s, str) or is_int(s) for s in ids
        ):
            content.splits_field.fail(str(name), "must be a list of sequence ids")
        split_ids[str(name)] = tuple(normalise(s) for s in ids)
    unlabeled = None
    if content.unlabeled is not None:
        value, where = content.unlabeled
        if not is_int(value) or not 0 <= value < n:
            f.fail(where, f"must be an integer 0..{n - 1}, got {value!r}")
        unlabeled = value
    return LabelConfig(
        class_names=tuple(c.name for c in classes),
        class_raw_ids=tuple(c.raw_id for c in classes),
        ignored=tuple(c.ignored for c in classes),
        raw_names={r.id: str(r.name) for r in content.raws},
        raw_to_class=raw_to_class,
        raw_bgr={r.id: tuple(r.bgr) for r in content.raws},
        raw_frequency={r.id: float(r.frequency) for r in content.raws},
        splits=split_ids,
        unlabeled_class=unlabeled,
    )


@cache
def semantickitti() -> LabelConfig:
    """The bundled SemanticKITTI configuration (20 training classes, class 0 ignored)."""
    return load_label_config(DATA_DIR / "semantickitti.json")
