"""`python -m workers.train_job` (or `rangeret train --ray`): data-parallel training on Ray Train.

    ray job submit --working-dir . -- python -m workers.train_job --dataset ROOT \\
        --profile pandaset --model rangeret-thesis --out DIR --workers 4

The training options are those of `rangeret train` (`rangeret.train_options`), `--config
FILE.yaml` and `--print-config` included.

ROOT is a tree in the layout of the dataset profile (`--profile`, SemanticKITTI by default).

Ray Train's TorchTrainer starts `--workers` training workers (one GPU each when the cluster has
GPUs, gloo on CPU workers, nccl on GPUs) and each runs `rangeret.training.Trainer` as one rank of
a torch.distributed group: DistributedDataParallel over the network, every epoch dealt out across
the ranks, validation matrices summed. Rank 0 writes DIR (last.pt, best.pt, the resume state,
the CSV logs and the curves), so on a multi-node cluster ROOT and DIR must be on storage every node
mounts. Each epoch's metrics are reported to Ray Train. A worker group restarted after a failure
(`--max-failures`) continues the saved run exactly.

Connects to the cluster in RAY_ADDRESS (set by `ray job submit`), or starts a local Ray.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from rangeret.commands import run_command
from rangeret.dataset.layout import DatasetLayoutError
from rangeret.inference.runtime.precision import resolve_precision
from rangeret.train_options import add_training_options, config_from_args
from rangeret.training import TrainConfig, Trainer
from rangeret.training.config import TrainConfigError, profile_reference
from rangeret.training.config_file import config_yaml
from rangeret.training.data import find_scans, training_profile
from rangeret.training.init_from import check_parent
from rangeret.training.state import STATE, check_run_folder, read_state
from workers.cluster import connect
from workers.pipeline import ClusterCapacityError
from workers.train_options import add_ray_options

log = logging.getLogger("workers.train_job")


def train_loop(config: dict[str, Any]) -> None:
    """Body of every Ray Train worker: one rank of the run `config` (a `TrainConfig` dict)."""
    import ray.train
    import ray.train.torch

    settings = TrainConfig.from_dict(config)
    if not settings.resume and (Path(settings.out) / STATE).exists():
        # The driver checked that DIR held no run at launch: this state is this run's own, left
        # by a worker group that failed, so the restarted group continues it.
        settings = dataclasses.replace(settings, resume=True)
    trainer = Trainer(settings, device=ray.train.torch.get_device(), on_epoch_end=ray.train.report)
    trainer.fit()


def use_gpus(device: str, workers: int) -> bool:
    """Whether the workers get one GPU each: --device cuda, or auto on a cluster with GPUs."""
    import ray

    gpus = int(ray.cluster_resources().get("GPU", 0))
    if device == "cpu" or (device == "auto" and gpus == 0):
        return False
    if gpus < workers:
        raise ClusterCapacityError(
            f"the Ray cluster has {gpus} GPU(s) for {workers} workers: pass --workers {gpus or 1}"
            + (" or --device cpu" if device == "auto" else "")
        )
    return True


def run_ray(config: TrainConfig, workers: int = 2, max_failures: int = 0) -> Path:
    """Train `config` on `workers` Ray Train workers; returns the output folder.

    The inputs are checked here first (a run already in DIR without resume, the profile, an
    `--init-from` checkpoint that does not fit, a saved run with other settings, missing scans or
    labels), so that bad input fails with its own message instead of inside the workers.
    """
    from ray.train import FailureConfig, RunConfig, ScalingConfig
    from ray.train.torch import TorchConfig, TorchTrainer

    if workers < 1:
        raise TrainConfigError(f"the number of workers must be at least 1, got {workers}")
    out = Path(config.out).resolve()
    config = dataclasses.replace(
        config,
        out=str(out),
        dataset=str(Path(config.dataset).resolve()),
        profile=profile_reference(config.profile),
    )
    state = check_run_folder(out, config.resume)
    profile = training_profile(config)
    config = check_parent(config, profile)
    if config.resume:
        read_state(state, config, profile)
    if not find_scans(config.dataset, config.train_sequences, "train", profile):
        raise DatasetLayoutError(f"no labelled training scan under {config.dataset}")
    find_scans(config.dataset, config.val_sequences, "valid", profile)

    connect(None)
    gpu = use_gpus(config.device, workers)
    precision = resolve_precision(config.precision, torch.device("cuda" if gpu else "cpu"))
    trainer = TorchTrainer(
        train_loop,
        train_loop_config=config.to_dict(),
        scaling_config=ScalingConfig(num_workers=workers, use_gpu=gpu),
        torch_config=TorchConfig(backend="nccl" if gpu else "gloo"),
        run_config=RunConfig(
            name="train",
            storage_path=str(out / "ray"),
            failure_config=FailureConfig(max_failures=max_failures),
        ),
    )
    log.info(
        "training %s (%s profile) on %d Ray workers (%s) in %s",
        config.model,
        profile.name,
        workers,
        "GPU" if gpu else "CPU",
        precision,
    )
    trainer.fit()
    return out


def build_parser() -> argparse.ArgumentParser:
    """The options of `rangeret train`, plus the job's own."""
    parser = argparse.ArgumentParser(
        prog="python -m workers.train_job", description=__doc__.split("\n\n")[0]
    )
    add_training_options(parser)
    add_ray_options(parser)
    parser.add_argument(
        "--max-failures",
        type=int,
        default=0,
        metavar="N",
        help="restart a failed worker group up to N times, continuing the saved run",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars, less logging")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: parse, train, and turn input errors into one-line messages and exit code 1."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING if args.quiet else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return run_command("train_job", _run, args)


def _run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    if args.print_config:
        print(config_yaml(config), end="")
        return 0
    out = run_ray(config, workers=args.workers, max_failures=args.max_failures)
    print(f"last checkpoint: {out / 'last.pt'}; best checkpoint: {out / 'best.pt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
