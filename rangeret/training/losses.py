"""Training losses on range images (thesis section 4.3, Eq. 4.4-4.9, Table 4.5).

- Class-weighted cross-entropy (Eq. 4.4). Weights come from the share f_c of points in each class:
  w_c = 1 / sqrt(f_c + 1e-3) by default. RangeNet++'s w_c = 1 / (f_c + 1e-3) is available too, but
  on SemanticKITTI it spans a factor of 260 between vegetation and motorcyclist, so with batch
  size 1 a few rare pixels decide the whole gradient of a step; the square root keeps the ranking
  and shrinks that span to 16. Mean over the labelled pixels, weighted as torch does it.
- Lovász-Softmax (Eq. 4.5-4.7): for each class c, the errors m_i(c) = |[y_i = c] - f_i(c)| of the
  softmax probabilities, and the Lovász extension of the Jaccard loss Delta_Jc evaluated at them:
  with the errors sorted in decreasing order (permutation pi), sum_i m_pi(i) g_i, where g_i is
  Delta_Jc of the i largest errors minus Delta_Jc of the i - 1 largest, and
  Delta_Jc(M) = |M| / |{y = c} union M| for a set M of mispredicted pixels. The mean runs over the
  classes present in the labelled pixels (the Lovász paper's choice: a class absent from the
  ground truth has no IoU to optimise).
- alpha-balanced focal loss (Eq. 4.9): -alpha_t (1 - p_t)^gamma log p_t, averaged over the
  labelled pixels, with gamma = 2 and alpha_c the class weights scaled to a largest value of 1,
  so alpha_t lies in [0, 1] as in Eq. 4.9 and rare classes keep their full weight.

The thesis's default is the equally weighted sum of the three. Pixels of the ignored unlabeled
class (`ignore_index`: unlabelled points and empty pixels; 0 for SemanticKITTI, the profile's
unlabeled class in general) take no part in any of them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

LOSSES = ("ce", "lovasz", "focal")
WEIGHTINGS = ("inverse-sqrt", "inverse", "none")
#: Added to class shares before inverting them (RangeNet++'s epsilon).
WEIGHT_EPS = 1e-3
FOCAL_GAMMA = 2.0


def class_weights(
    frequencies: np.ndarray | Sequence[float],
    ignored: Sequence[bool],
    kind: str = "inverse-sqrt",
    eps: float = WEIGHT_EPS,
) -> torch.Tensor:
    """(C,) float32 weights from the shares of points per class; ignored classes get 0.

    `kind` is "inverse-sqrt" (1 / sqrt(f + eps)), "inverse" (1 / (f + eps)) or "none" (all 1).
    """
    freq = np.asarray(frequencies, dtype=np.float64)
    if kind == "inverse-sqrt":
        weights = 1.0 / np.sqrt(freq + eps)
    elif kind == "inverse":
        weights = 1.0 / (freq + eps)
    elif kind == "none":
        weights = np.ones_like(freq)
    else:
        raise ValueError(f"unknown class weighting {kind!r}; known: {', '.join(WEIGHTINGS)}")
    weights[np.asarray(ignored, dtype=bool)] = 0.0
    return torch.tensor(weights, dtype=torch.float32)


def weighted_cross_entropy(
    logits: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor, ignore_index: int = 0
) -> torch.Tensor:
    """Eq. 4.4 over (B, C, H, W) logits and (B, H, W) labels, weighted mean over labelled pixels
    (torch's weighted mean; 0 when no pixel is labelled)."""
    keep = labels != ignore_index
    per_pixel = F.cross_entropy(
        logits, labels, weight=weights, ignore_index=ignore_index, reduction="none"
    )
    total = weights.to(per_pixel.dtype)[torch.where(keep, labels, 0)] * keep
    return per_pixel.sum() / total.sum().clamp_min(torch.finfo(per_pixel.dtype).tiny)


def focal_loss(
    logits: torch.Tensor,
    labels: torch.Tensor,
    alpha: torch.Tensor,
    gamma: float = FOCAL_GAMMA,
    ignore_index: int = 0,
) -> torch.Tensor:
    """Eq. 4.9: mean over labelled pixels of -alpha_t (1 - p_t)^gamma log p_t; `alpha` is (C,)."""
    log_p = F.log_softmax(logits, dim=1)
    keep = labels != ignore_index
    target = torch.where(keep, labels, 0)
    log_pt = log_p.gather(1, target.unsqueeze(1)).squeeze(1)
    pt = log_pt.exp()
    alpha_t = alpha.to(logits.dtype)[target] * keep
    return (-alpha_t * (1.0 - pt).pow(gamma) * log_pt).sum() / keep.sum().clamp_min(1)


def lovasz_gradient(sorted_truth: torch.Tensor) -> torch.Tensor:
    """g_i for ground truth sorted by decreasing error, along dim 0: the increments of Delta_J.

    For the i largest errors, |{y = c} union M_i| = |{y = c}| + (number of background pixels among
    them) and the intersection of prediction and truth is |{y = c}| - (foreground pixels among
    them), so Delta_J(prefix i) = 1 - intersection / union, and g_i is its difference along i.
    """
    total = sorted_truth.sum(dim=0, keepdim=True)
    intersection = total - sorted_truth.cumsum(dim=0)
    union = total + (1.0 - sorted_truth).cumsum(dim=0)
    jaccard = 1.0 - intersection / union
    return torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]], dim=0)


def lovasz_softmax(
    probabilities: torch.Tensor, labels: torch.Tensor, ignore_index: int = 0
) -> torch.Tensor:
    """Eq. 4.7 over (B, C, H, W) probabilities (or (P, C)) and (B, H, W) (or (P,)) labels.

    Averaged over the classes present among the labelled pixels; 0 when no pixel is labelled.
    Unlabelled pixels keep their place with error 0 and no class, so they sort after every error
    that counts and change no term; with the classes masked rather than selected, no shape
    depends on the data and the loss needs no host synchronisation.
    """
    if probabilities.dim() == 4:
        probabilities = probabilities.permute(0, 2, 3, 1).reshape(-1, probabilities.shape[1])
    labels = labels.reshape(-1)
    keep = (labels != ignore_index).unsqueeze(1)
    classes = torch.arange(probabilities.shape[1], device=labels.device)
    truth = ((labels[:, None] == classes[None, :]) & keep).to(probabilities.dtype)
    errors = (truth - probabilities).abs() * keep
    sorted_errors, order = torch.sort(errors, dim=0, descending=True)
    sorted_truth = truth.gather(0, order)
    per_class = (sorted_errors * lovasz_gradient(sorted_truth)).sum(dim=0)
    present = truth.sum(dim=0) > 0
    return (per_class * present).sum() / present.sum().clamp_min(1)


class SegmentationLoss(nn.Module):
    """The equally weighted sum of the chosen losses; `forward` also returns each term's value."""

    def __init__(
        self,
        losses: Sequence[str],
        weights: torch.Tensor,
        gamma: float = FOCAL_GAMMA,
        ignore_index: int = 0,
    ) -> None:
        super().__init__()
        unknown = sorted(set(losses) - set(LOSSES))
        if unknown or not losses:
            raise ValueError(
                f"losses must be a non-empty selection of {', '.join(LOSSES)}, got {list(losses)}"
            )
        self.losses = tuple(name for name in LOSSES if name in losses)
        self.gamma = gamma
        self.ignore_index = ignore_index
        self.register_buffer("weights", weights.float().clone())
        peak = float(weights.max()) if weights.numel() and float(weights.max()) > 0 else 1.0
        self.register_buffer("alpha", weights.float() / peak)

    def forward(
        self, logits: torch.Tensor, labels: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(total, {name: term}) for (B, C, H, W) logits and (B, H, W) int64 labels (computed in fp32)."""
        logits = logits.float()
        terms: dict[str, torch.Tensor] = {}
        if "ce" in self.losses:
            terms["ce"] = weighted_cross_entropy(logits, labels, self.weights, self.ignore_index)
        if "lovasz" in self.losses:
            terms["lovasz"] = lovasz_softmax(logits.softmax(dim=1), labels, self.ignore_index)
        if "focal" in self.losses:
            terms["focal"] = focal_loss(logits, labels, self.alpha, self.gamma, self.ignore_index)
        return sum(terms.values()), terms
