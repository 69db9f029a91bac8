"""GET /v1/model and /v1/models: which networks the gateway serves, from which checkpoints,
whether those are the bundled demo weights, and the precision each runs at and why.

The gateway knows its checkpoint from loading it at start (also when the network itself runs on
the Serve application, which is checked to serve the same file), so the answer comes from it and
needs no worker. The web page shows the note beside the model's name.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter

from rangeret.exceptions import RangeRetError
from rangeret.inference.runtime.device import select_device
from rangeret.inference.runtime.precision import PrecisionChoice, choose_precision
from rangeret.models.weights.demo import is_demo_checkpoint, real_weights_hint
from service.gateway import Gateway
from service.http.dependencies import GatewayDep
from service.http.errors import error_responses
from service.models.catalog import MODEL_QUERY, ModelEntry
from service.served_schemas import ListedModel, ModelList, ServedModel

router = APIRouter(prefix="/v1", tags=["service"])


def demo_note(profile: str) -> str:
    """What the page shows beside the model's name when demo weights are served: real weights
    for the model's own profile (a published one, or a network trained on it)."""
    return (
        "Demo weights: trained on simulated scenes only, so their labels of real scans are not "
        f"meaningful. Serve real weights with rangeret serve {real_weights_hint(profile)}."
    )


def served_model(gw: Gateway, entry: ModelEntry, network: str | None) -> ServedModel:
    """What the gateway says of one model: its network, checkpoint, profile, demo note and the
    precision it runs at, with why."""
    demo = is_demo_checkpoint(entry.checkpoint_sha256)
    precision = served_precision(gw, entry)
    return ServedModel(
        id=entry.name,
        name=network,
        checkpoint_sha256=entry.checkpoint_sha256,
        profile=entry.profile.name,
        demo_weights=demo,
        note=demo_note(entry.profile.name) if demo else None,
        precision=None if precision is None else precision.precision,
        precision_reason=None if precision is None else precision.reason,
    )


def served_precision(gw: Gateway, entry: ModelEntry) -> PrecisionChoice | None:
    """The precision the model's network runs at in this process and why: its --precision
    resolved on the device it runs on here, as its predictor resolves it when loaded. None where
    the Serve application runs it (with its own options, on its own machine)."""
    if gw.labeller.backend != "local":
        return None
    spec = entry.spec
    try:
        return choose_precision(spec.precision, select_device(spec.device), spec.backend)
    except RangeRetError:  # a device or backend this machine lacks: the model cannot load here
        return None


async def network_name(gw: Gateway, entry: ModelEntry) -> str | None:
    """The model's network name: known from loading it at start, else from the workers."""
    if entry.network is not None:
        return entry.network
    workers = (await gw.labeller.health()).get("workers", [])
    return next((w["model"] for w in workers if w.get("model")), None)


@router.get(
    "/model",
    summary="A served network and its checkpoint",
    description=(
        "The network of the model `model` (the default without it): its name, its checkpoint's "
        "SHA-256, its profile and whether these are the bundled demo weights (trained on "
        "simulated scenes only), with a note saying how to serve a published model instead, and "
        "the precision its forward pass runs at on this machine, with why."
    ),
    operation_id="get_model",
    response_model=ServedModel,
    responses=error_responses(400, 404),
)
async def model(gw: GatewayDep, model: Annotated[str | None, MODEL_QUERY] = None) -> ServedModel:
    entry = gw.models.get(model)
    return served_model(gw, entry, await network_name(gw, entry))


@router.get(
    "/models",
    summary="Every served model",
    description=(
        "The models this gateway serves, in its models file's order, each as `GET /v1/model` "
        "describes it and whether its network is loaded now, and the default one."
    ),
    operation_id="list_models",
    response_model=ModelList,
    responses=error_responses(400),
)
async def models(gw: GatewayDep) -> ModelList:
    loaded = gw.loaded_models()
    listed = [
        ListedModel(
            **served_model(gw, entry, await network_name(gw, entry)).model_dump(),
            loaded=loaded is None or entry.name in loaded,
        )
        for entry in gw.models
    ]
    return ModelList(default=gw.models.default, models=listed)
