"""Training RangeRet networks with the thesis's recipe (chapters 3.4 and 4).

- `config`: `TrainConfig`, the run as plain data, with its dataset profile (SemanticKITTI by
  default; any profile's layout, point record, projection, labels and kNN rule).
- `data`: a profile's scans as range images with per-pixel training classes, seeded per
  (epoch, scan) so runs and resumes are reproducible.
- `augment`: the thesis's point augmentations (scale, rotation, shift, flip of x and y).
- `range_mixes`: RangeFormer's range-image mixes (RangeMix, RangeUnion, RangePaste, RangeShift).
- `losses`: class-weighted cross-entropy, Lovász-Softmax, alpha-balanced focal loss, and their sum.
- `schedule`: AdamW with OneCycle or warm-up + cosine.
- `trainer`: the loop, validation (range image, points, points + kNN), checkpoints, exact resume,
  and data-parallel ranks under torch.distributed.

The `rangeret train` command lives in `rangeret.cli.train`. The library never imports Ray: `workers.train_job` runs `Trainer` on Ray Train workers.
"""

from rangeret.training.config import TrainConfig
from rangeret.training.trainer import Trainer, TrainResult

__all__ = [
    "TrainConfig",
    "TrainResult",
    "Trainer",
]
