"""`python -m workers.adapt_job`: resample a whole labelled dataset to another sensor on Ray.

    ray job submit --working-dir . -- python -m workers.adapt_job --dataset /data/kitti \\
        --profile semantickitti --to-profile /profiles/my-sensor.yaml --split train \\
        --out /data/kitti-as-my-sensor

It takes `rangeret adapt`'s options and runs its steps: the driver plans the run (profiles, label
map, scans, `OUT/adapt.json`), Ray tasks adapt one scan each (`rangeret.adapt.adapt_one`, the
step the command runs in its own process), and the driver writes the record. Connects to the
cluster in RAY_ADDRESS (set by `ray job submit`), or starts a local Ray when none is set; on a
multi-node cluster ROOT and OUT must be on storage every node mounts. Scans adapted by an
earlier run with the same settings are skipped (resume). A scan that cannot be adapted (an
unknown raw id, say) stops the job with one line naming it; what was written stays.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from rangeret.adapt import AdaptSettings, AdaptStats, ScanJob, adapt_one, finish, summary
from rangeret.commands import CommandError, run_command
from rangeret.exceptions import RangeRetError
from rangeret.options import adapt_plan_from_args, add_adapt_options, add_output_options
from workers.cluster import connect

log = logging.getLogger("workers.adapt_job")

#: Scans in flight per CPU of the cluster: enough to keep every worker busy between waits.
IN_FLIGHT_PER_CPU = 2


def build_parser() -> argparse.ArgumentParser:
    """`rangeret adapt`'s options, and the CPUs each scan's task takes."""
    p = argparse.ArgumentParser(
        prog="python -m workers.adapt_job", description=__doc__.split("\n\n")[0]
    )
    add_adapt_options(p)
    p.add_argument(
        "--task-cpus",
        type=float,
        default=1.0,
        metavar="N",
        help="CPUs each scan's task reserves (default: 1)",
    )
    add_output_options(p)
    return p


def _adapt_task(job: ScanJob, settings: AdaptSettings) -> AdaptStats:
    """One scan, on a Ray worker: the library's own step."""
    return adapt_one(job, settings)


def run(args: argparse.Namespace) -> int:
    """Plan on the driver, adapt the scans as Ray tasks, record and report on the driver."""
    import ray

    if not args.task_cpus > 0:
        raise CommandError(f"--task-cpus must be positive, got {args.task_cpus:g}")
    plan = adapt_plan_from_args(args)
    todo = plan.todo
    log.info(
        "%d scans of %s: %d to adapt, %d already done",
        len(plan.jobs),
        ", ".join(plan.sequences),
        len(todo),
        plan.skipped,
    )
    results: list[AdaptStats] = []
    if todo:
        connect(None)
        task = ray.remote(num_cpus=args.task_cpus, max_retries=1)(_adapt_task)
        settings = ray.put(plan.settings)
        window = max(1, int(ray.cluster_resources().get("CPU", 1) * IN_FLIGHT_PER_CPU))
        results = _gather(task, settings, todo, window, progress=not args.quiet)
    print(summary(plan, results, finish(plan, results)))
    return 0


def _gather(
    task: object, settings: object, todo: list[ScanJob], window: int, *, progress: bool
) -> list[AdaptStats]:
    """Run `task` on every job, at most `window` at a time, and collect their counts; the first
    scan that fails cancels the rest and raises its own error (one line), not Ray's wrapper."""
    import ray
    from tqdm import tqdm

    pending = list(reversed(todo))
    running: list[ray.ObjectRef] = []
    results: list[AdaptStats] = []
    with tqdm(total=len(todo), unit="scan", desc="adapting", disable=not progress) as bar:
        while pending or running:
            while pending and len(running) < window:
                running.append(task.remote(pending.pop(), settings))  # type: ignore[attr-defined]
            done, running = ray.wait(running, num_returns=1)
            try:
                results.append(ray.get(done[0]))
            except ray.exceptions.RayTaskError as exc:
                for ref in running:
                    ray.cancel(ref)
                cause = exc.cause
                if isinstance(cause, RangeRetError):
                    raise cause from None
                raise
            bar.update(1)
    return results


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: parse, run, and turn input errors into one-line messages and exit code 1."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return run_command("adapt_job", run, args)


if __name__ == "__main__":
    sys.exit(main())
