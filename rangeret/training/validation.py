"""Validation of a network at an epoch's end: the loss, and mIoU / accuracy on the range image
(labelled pixels), on the points (each point takes its pixel's class) and on the points after
kNN refinement with the profile's voting rule (`rangeret.inference.point_labels.
point_classes_batch`), with the official semantics of `rangeret.evaluation.metrics`.

Confusion counts stay on the device until every batch is seen; under data parallelism they are
summed across ranks before the metrics are taken.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import torch
from tqdm import tqdm

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.metrics import ConfusionMatrix
from rangeret.inference.point_labels import pixel_classes, point_classes_batch
from rangeret.inference.runtime.precision import forward_precision
from rangeret.inference.settings import KnnSettings
from rangeret.training.distributed import Ranks
from rangeret.training.losses import SegmentationLoss

VAL_METRICS = (
    "val_loss",
    "val_miou_image",
    "val_acc_image",
    "val_miou_points",
    "val_acc_points",
    "val_miou_knn",
    "val_acc_knn",
)


def confusion_matrix(flat: torch.Tensor, label_config: LabelConfig) -> ConfusionMatrix:
    """A ConfusionMatrix of the label configuration from flat C[pred, gt] counts."""
    c = label_config.num_classes
    cm = ConfusionMatrix.for_config(config=label_config)
    cm.merge(flat.reshape(c, c).cpu().numpy())
    return cm


@torch.inference_mode()
def validate(
    model: torch.nn.Module,
    criterion: SegmentationLoss,
    batches: Iterable[Mapping[str, Any]],
    *,
    profile: DatasetProfile,
    knn: KnnSettings,
    precision: str,
    device: torch.device,
    ranks: Ranks,
    progress: tqdm,
) -> dict[str, float]:
    """`VAL_METRICS` of `model` over `batches` (collated validation samples with their points),
    summed over `ranks`; `progress` advances by the scans of each batch."""
    model.eval()
    c = profile.num_classes
    rule = {"votes_from": profile.knn.votes_from, "unlabeled": profile.labels.unlabeled_class}
    counts = torch.zeros(3, c * c, dtype=torch.int64, device=device)
    loss_sum = torch.zeros(2, dtype=torch.float64, device=device)
    for batch in batches:
        images = batch["image"].to(device)
        labels = batch["label"].to(device)
        with forward_precision(precision, device):
            logits = model(images)
        loss, _ = criterion(logits, labels)
        loss_sum[0] += loss.double() * len(images)
        loss_sum[1] += len(images)
        argmax = pixel_classes(logits)
        counts[0] += torch.bincount((argmax * c + labels).reshape(-1), minlength=c * c)
        for i in range(len(images)):
            truth = batch["point_labels"][i].to(device)
            projection = (
                [batch["proj_x"][i]],
                [batch["proj_y"][i]],
                [batch["proj_range"][i]],
                [batch["unproj_range"][i]],
            )
            scan = argmax[i : i + 1]
            points = point_classes_batch(scan, *projection, None, c, **rule)
            refined = point_classes_batch(scan, *projection, knn, c, **rule)
            counts[1] += torch.bincount(points * c + truth, minlength=c * c)
            counts[2] += torch.bincount(refined.to(truth.dtype) * c + truth, minlength=c * c)
        progress.update(len(images))
    counts = ranks.sum(counts)
    loss_sum = ranks.sum(loss_sum).cpu()
    image, points, refined = (confusion_matrix(counts[i], profile.labels) for i in range(3))
    return {
        "val_loss": float(loss_sum[0] / max(loss_sum[1], 1)),
        "val_miou_image": image.miou(),
        "val_acc_image": image.accuracy(),
        "val_miou_points": points.miou(),
        "val_acc_points": points.accuracy(),
        "val_miou_knn": refined.miou(),
        "val_acc_knn": refined.accuracy(),
    }
