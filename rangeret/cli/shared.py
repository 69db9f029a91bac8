"""What several `rangeret` commands share: the loaded predictor of the network options."""

from __future__ import annotations

import argparse
import logging
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
    with export_heartbeat(not getattr(args, "quiet", False)):
        predictor = Predictor.from_spec(spec)
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
