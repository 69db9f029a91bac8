"""Training RangeRet networks with the thesis's recipe (chapters 3.4 and 4).

- `config`: `TrainConfig`, the run as plain data, with its dataset profile (SemanticKITTI by
  default; any profile's layout, point record, projection, labels and kNN rule); each field
  carries its command-line help, so the options and the file are derived from it.
- `config_file`: a `TrainConfig` as YAML (`--config`, `--print-config`), checked key by key.
- `data`: a profile's scans (found in its layout) as range images with per-pixel training
  classes, seeded per (epoch, scan) so runs and resumes are reproducible.
- `augment`: the thesis's point augmentations (scale, rotation, shift, flip of x and y).
- `range_mixes`: RangeFormer's range-image mixes (RangeMix, RangeUnion, RangePaste, RangeShift).
- `losses`: class-weighted cross-entropy, Lovász-Softmax, alpha-balanced focal loss, and their sum.
- `schedule`: the named optimiser (AdamW) and schedules (OneCycle, warm-up + cosine).
- `distributed`: data-parallel ranks under torch.distributed, and DDP's unused-parameter search.
- `state`: the run folder's files, the resume state, its checks and the random states.
- `validation`: loss and mIoU / accuracy on the range image, the points and the points + kNN.
- `trainer`: the loop, epoch ends, checkpoints and exact resume.

The options of `rangeret train` are derived in `rangeret.train_options`; the command lives in
`rangeret.cli.train`. The library never imports Ray: `workers.train_job` runs `Trainer` on Ray Train workers.
"""

from rangeret.training.config import TrainConfig
from rangeret.training.trainer import Trainer, TrainResult

__all__ = [
    "TrainConfig",
    "TrainResult",
    "Trainer",
]
