"""GET /v1/profile: the served profile's point record, classes, palette and learning map.

The web page reads it to draw scans in the profile's colours and to score a prediction against a
ground-truth file with the benchmark's rules; any client can use it the same way.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter

from rangeret.dataset.profiles import DatasetProfile
from service.http.dependencies import GatewayDep
from service.http.errors import error_responses
from service.labelling.panoptic import panoptic_dtype
from service.models.catalog import MODEL_QUERY
from service.served_schemas import PanopticLabels, ProfileClass, ServedProfile

router = APIRouter(prefix="/v1", tags=["service"])


def served_profile(profile: DatasetProfile) -> ServedProfile:
    """The API form of a dataset profile: classes with RGB colours, and the raw-id map."""
    labels = profile.labels
    rgb = labels.class_rgb()
    classes = [
        ProfileClass(
            index=index,
            name=name,
            raw_id=labels.class_raw_ids[index],
            color="#{:02x}{:02x}{:02x}".format(*(int(v) for v in rgb[index])),
            ignored=labels.ignored[index],
        )
        for index, name in enumerate(labels.class_names)
    ]
    return ServedProfile(
        profile=profile.name,
        point_fields=list(profile.points.fields),
        point_bytes=profile.points.point_bytes,
        label_bytes=profile.layout.label_file.bytes,
        predictions=profile.benchmark.predictions,
        classes=classes,
        raw_to_class={str(raw): cls for raw, cls in sorted(labels.raw_to_class.items())},
        unlabeled_class=labels.unlabeled_class,
        panoptic=panoptic_labels(profile),
    )


def panoptic_labels(profile: DatasetProfile) -> PanopticLabels | None:
    """How the profile's panoptic answers pack objects into labels; None without thing classes."""
    if profile.panoptic_refusal() is not None:
        return None
    encoding = profile.layout.panoptic_encoding
    return PanopticLabels(
        benchmark=profile.benchmark.panoptic,
        things=profile.thing_names,
        label_bytes=panoptic_dtype(profile).itemsize,
        multiplier=encoding.multiplier,
        instance_high=encoding.instance_high,
    )


@router.get(
    "/profile",
    summary="A model's profile: classes, palette and label map",
    description=(
        "The dataset profile of the model `model` (the default without it): its point record, "
        "how wide its labels are and what a prediction holds, its training classes (name, raw "
        "id, colour as #rrggbb, ignored or not) and the map from raw ids to classes, as the "
        "evaluation uses them: enough to colour a scan's labels and to score a prediction "
        "against ground truth the way the benchmark does; and, where it names thing classes, "
        "how its panoptic labels pack a point's object."
    ),
    operation_id="get_profile",
    response_model=ServedProfile,
    responses=error_responses(400, 404),
)
async def profile(
    gw: GatewayDep, model: Annotated[str | None, MODEL_QUERY] = None
) -> ServedProfile:
    return served_profile(gw.models.get(model).profile)
