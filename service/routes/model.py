"""GET /v1/model: which network the gateway serves, from which checkpoint, and whether those are
the bundled demo weights.

The gateway knows its checkpoint from loading it at start (also when the network itself runs on
the Serve application, which is checked to serve the same file), so the answer comes from it and
needs no worker. The web page shows the note beside the model's name.
"""

from __future__ import annotations

from fastapi import APIRouter

from rangeret.models.weights.demo import is_demo_checkpoint
from service.dependencies import GatewayDep
from service.errors import error_responses
from service.schemas import ServedModel

router = APIRouter(prefix="/v1", tags=["service"])

#: What the page shows beside the model's name when the demo weights are served.
DEMO_NOTE = (
    "Demo weights: trained on simulated scenes only, so their labels of real scans are not "
    "meaningful. Serve a published model with rangeret serve --checkpoint rangeret-kitti-657 "
    "(see rangeret weights list)."
)


@router.get(
    "/model",
    summary="The served network and its checkpoint",
    description=(
        "The served network's name, its checkpoint's SHA-256 and whether these are the bundled "
        "demo weights (trained on simulated scenes only), with a note saying how to serve a "
        "published model instead."
    ),
    operation_id="get_model",
    response_model=ServedModel,
    responses=error_responses(400),
)
async def model(gw: GatewayDep) -> ServedModel:
    name = gw.model
    if name is None:
        workers = (await gw.labeller.health()).get("workers", [])
        name = next((w["model"] for w in workers if w.get("model")), None)
    demo = is_demo_checkpoint(gw.checkpoint_sha256)
    return ServedModel(
        name=name,
        checkpoint_sha256=gw.checkpoint_sha256,
        profile=gw.profile.name,
        demo_weights=demo,
        note=DEMO_NOTE if demo else None,
    )
