"""What several `rangeret` commands share: the loaded predictor of the network options."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.inference.spec import InferenceSpec

if TYPE_CHECKING:
    from rangeret.inference.predictor import Predictor

log = logging.getLogger("rangeret")


def predictor_from_args(args: argparse.Namespace) -> Predictor:
    """A loaded `Predictor` from the shared network options, announced in the log (a first
    onnxruntime export says how long it has run, except with -q)."""
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.runtime.onnx_backend import export_heartbeat

    spec = InferenceSpec.from_args(args)
    label_map = getattr(args, "label_map", None)
    with export_heartbeat(not getattr(args, "quiet", False)):
        if label_map is None:
            predictor = Predictor.from_spec(spec)
        else:
            predictor = _predictor_for_data(spec, label_map)
    info = predictor.describe()
    log.info(
        "%s from %s (sha256 %s), %s profile, at %dx%d on %s",
        info["model"],
        info["checkpoint"],
        (info["checkpoint_sha256"] or "")[:12],
        predictor.profile.name,
        predictor.projection_config.height,
        predictor.projection_config.width,
        predictor.device,
    )
    return predictor


def _predictor_for_data(spec: InferenceSpec, label_map: Path) -> Predictor:
    """The predictor of `spec`'s network on the dataset of `spec.profile` (another sensor's):
    the network loaded with its own profile, the data's projection options (--height, --width,
    --fov-up, --fov-down) applied to the data's profile, and the network's raw ids mapped."""
    from rangeret.dataset.label_map import load_label_map
    from rangeret.dataset.profiles import load_profile
    from rangeret.inference.predictor import Predictor

    data = load_profile(spec.profile).with_overrides(
        height=spec.height, width=spec.width, fov_up=spec.fov_up, fov_down=spec.fov_down
    )
    network = spec.replace(profile=None, height=None, width=None, fov_up=None, fov_down=None)
    return Predictor.from_spec(network).for_data(data, load_label_map(label_map, data))
