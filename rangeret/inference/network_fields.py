"""The fields a network run (`InferenceSpec`) and a training run (`TrainConfig`) share, each
declared once: the dataset profile, the network, the range image's rows, columns and vertical
field of view, and how the network's passes run (scans per pass, device, precision: fp32 unless
asked for in a network run, auto in a training run).

A `FieldSchema` holds a field's name, kind, default, allowed values (choices, or the least and the
most integer) and help. `rangeret.inference.spec` declares every field of `InferenceSpec` with
one, `rangeret.training.config` these nine of `TrainConfig`'s, so both check a value with the
same sentence (`FieldSchema.problem`) and their options help with the same words
(`option_help`). Torch-free, since every `rangeret` call builds its parser from it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from rangeret.dataset.profiles import BUILTIN_PROFILES
from rangeret.dataset.projection import MAX_HEIGHT, MAX_WIDTH
from rangeret.inference.runtime.precision import PRECISIONS

#: The networks a checkpoint can hold: `rangeret.models.list_models()`, which imports torch.
MODELS = ("rangeret-cir", "rangeret-thesis")
#: Where the network runs.
DEVICES = ("auto", "cpu", "cuda")
#: How a message names the value each kind of field takes.
KIND_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


@dataclass(frozen=True)
class FieldSchema:
    """One field as a dataclass declares it: `kind` (bool, int, float or str; None is allowed
    where the default is None), `default`, `default_text` (what the help says the default is,
    where the value alone does not say it), the option's `metavar`, the `choices` it takes, or
    the least and the most integer (`minimum`, `maximum`), and `help`."""

    name: str
    kind: type
    help: str
    default: Any = None
    default_text: str | None = None
    metavar: str | None = None
    choices: tuple[str, ...] | None = None
    minimum: int | None = None
    maximum: int | None = None

    def problem(self, value: Any, name: str | None = None) -> str | None:
        """What is wrong with `value` for this field, as one sentence naming the field as `name`
        (default: its own name); None when it can be used."""
        name = name or self.name
        if value is None:
            return None
        if self.choices is not None and value not in self.choices:
            return f"{name} must be one of {', '.join(self.choices)}, got {value!r}"
        if self.minimum is not None and value < self.minimum:
            least = "not be negative" if self.minimum == 0 else f"be at least {self.minimum}"
            return f"{name} must {least}, got {value}"
        if self.maximum is not None and value > self.maximum:
            return f"{name} must be at most {self.maximum}, got {value}"
        return None

    def field(self, *, note: str = "", **metadata: Any) -> Any:
        """A dataclass field of this schema: its default, and metadata holding the schema, its
        help (`note` after it, where the declaring class says more), metavar, choices and
        default text, with the declaring class's own `metadata` (its option group, say)."""
        return dataclasses.field(
            default=self.default,
            metadata={
                "schema": self,
                "help": f"{self.help}; {note}" if note else self.help,
                "metavar": self.metavar,
                "choices": self.choices,
                "default_text": self.default_text,
                **metadata,
            },
        )


def option_help(f: dataclasses.Field) -> str:
    """The help of a field's command-line option: its `help` metadata and the default it shows
    (its `default_text`, else the value itself; none for a required field, a flag, an empty list
    or None), with `%` escaped for argparse."""
    shown = f.metadata.get("default_text")
    value = f.default
    if shown is None and not (
        f.metadata.get("required")
        or value is dataclasses.MISSING
        or value is None
        or isinstance(value, bool)
        or value == ()
    ):
        shown = " ".join(map(str, value)) if isinstance(value, tuple) else str(value)
    text = f"{f.metadata['help']} (default: {shown})" if shown else f.metadata["help"]
    return text.replace("%", "%%")


PROFILE = FieldSchema(
    "profile",
    str,
    f"dataset profile: {', '.join(BUILTIN_PROFILES)} or a YAML file; `rangeret profile show NAME` "
    "prints one to start from",
    default_text="the checkpoint's, else semantickitti",
    metavar="NAME|FILE",
)
MODEL = FieldSchema(
    "model", str, "network name", default_text="recognised from the checkpoint", choices=MODELS
)
HEIGHT = FieldSchema(
    "height",
    int,
    f"range image rows, at most {MAX_HEIGHT}",
    default_text="the profile's",
    minimum=1,
    maximum=MAX_HEIGHT,
)
WIDTH = FieldSchema(
    "width",
    int,
    f"range image columns, at most {MAX_WIDTH}",
    default_text="the profile's",
    minimum=1,
    maximum=MAX_WIDTH,
)
FOV_UP = FieldSchema(
    "fov_up",
    float,
    "upper vertical field of view",
    default_text="the profile's",
    metavar="DEG",
)
FOV_DOWN = FieldSchema(
    "fov_down",
    float,
    "lower vertical field of view",
    default_text="the profile's",
    metavar="DEG",
)
BATCH_SIZE = FieldSchema(
    "batch_size", int, "scans per network pass", default=1, metavar="N", minimum=1
)
DEVICE = FieldSchema("device", str, "auto picks CUDA when present", default="auto", choices=DEVICES)
#: What `--precision auto` picks (`rangeret.inference.runtime.precision.auto_choice`).
AUTO_RULE = (
    "auto is bf16 where the CPU (AMX or AVX-512 bf16) or the CUDA device runs bf16 natively, "
    "fp32 elsewhere"
)
PRECISION = FieldSchema(
    "precision",
    str,
    f"precision of the network's passes; {AUTO_RULE}",
    default="fp32",
    choices=PRECISIONS,
)
#: A training run's precision: mixed precision by the auto rule unless another is asked for.
TRAINING_PRECISION = dataclasses.replace(PRECISION, default="auto")
