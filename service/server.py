"""`rangeret serve`: build the worker pool and the job executor, then run the gateway on uvicorn.

With a Ray address (`--ray-address` or RANGERET_RAY_ADDRESS) single scans go to the model actors of
`workers.pool.ScanPool` and jobs to the Ray pipeline; without one, both run in this process
(`LocalScanPool`, `predict_tree`). Options given on the command line win over RANGERET_* variables.
The gateway serves one dataset profile: the checkpoint's, or the one given with `--profile`.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass, replace

from pydantic import ValidationError

from rangeret.errors import CommandError
from rangeret.inference import PredictorSpec, checkpoint_profile
from rangeret.options import add_network_options, spec_from_args
from rangeret.profiles import DatasetProfile
from service.errors import validation_sentence
from service.settings import Settings

log = logging.getLogger("rangeret.serve")

#: Options of `serve` that override the settings of the same name.
_OVERRIDES = (
    "host",
    "port",
    "batch_size",
    "batch_wait_ms",
    "ray_address",
    "actors",
    "root_path",
)


def add_serve_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `rangeret serve`: address, batching, Ray backend, and the shared network options."""
    g = parser.add_argument_group("gateway")
    g.add_argument(
        "--host", help="address to listen on (default 127.0.0.1; another needs RANGERET_API_TOKEN)"
    )
    g.add_argument("--port", type=int, help="port to listen on (default 8000)")
    g.add_argument(
        "--batch-wait-ms",
        type=float,
        metavar="MS",
        help="longest a single-scan request waits for others to fill its batch (default 10)",
    )
    g.add_argument(
        "--ray-address",
        metavar="ADDR",
        help="Ray cluster for the workers ('auto' or host:port); default: run them in this process",
    )
    g.add_argument(
        "--actors",
        type=int,
        metavar="N",
        help="model actors on the Ray cluster (default: one per GPU, or 1)",
    )
    g.add_argument(
        "--root-path",
        metavar="PREFIX",
        help="path prefix a reverse proxy serves the gateway under, such as /rangeret (default none)",
    )
    g.add_argument(
        "--log-level",
        default="info",
        choices=["critical", "error", "warning", "info", "debug"],
        help="uvicorn's log level (default info)",
    )
    add_network_options(parser)
    parser.set_defaults(batch_size=None)  # unset: RANGERET_BATCH_SIZE, else 1


def settings_from_args(args: argparse.Namespace) -> Settings:
    """The settings from RANGERET_* variables, with the command line's options on top."""
    overrides = {
        name: getattr(args, name) for name in _OVERRIDES if getattr(args, name, None) is not None
    }
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        raise CommandError(validation_sentence(exc.errors(), "setting")) from exc


@dataclass(frozen=True)
class CheckpointFacts:
    """What the gateway needs to know about the weights without running them."""

    profile: DatasetProfile
    sha256: str
    model: str


def checkpoint_facts(spec: PredictorSpec) -> CheckpointFacts:
    """Load the checkpoint once to check it and resolve the profile it runs with, and its hash."""
    info, profile = checkpoint_profile(spec)
    return CheckpointFacts(profile, info.sha256, info.name)


def build_backend(settings: Settings, spec: PredictorSpec, facts: CheckpointFacts):
    """The single-scan pool, the job executor and the number of batch dispatchers, all running
    the network with the served profile. On a GPU cluster the pool's actors (one per GPU unless
    `actors` says otherwise) also run the jobs, so a job never waits for a GPU the pool holds."""
    from service.jobs import LocalExecutor, RayExecutor
    from workers.pool import LocalScanPool, ScanPool

    served = replace(spec, profile=facts.profile)
    if settings.ray_address:
        import ray

        if not ray.is_initialized():
            ray.init(address=settings.ray_address, log_to_driver=False)
        use_gpu = None if spec.device == "auto" else spec.device == "cuda"
        pool = ScanPool(served, actors=settings.actors, use_gpu=use_gpu)
        executor = RayExecutor(
            served, facts.profile, settings.batch_size, settings.actors, pool=pool
        )
        return pool, executor, len(pool.actors)
    return LocalScanPool(served), LocalExecutor(served, settings.batch_size), 1


def run_serve(args: argparse.Namespace) -> int:
    """Run the gateway until it is stopped (Ctrl-C or SIGTERM); returns the exit code."""
    import uvicorn

    from service.app import create_app
    from service.protocols import GatewayProtocol

    settings = settings_from_args(args)
    problem = settings.address_problem()
    if problem:
        raise CommandError(problem)
    from service.jobs import check_schema_version

    check_schema_version(settings.database_path)  # before minutes of loading weights and workers
    args.batch_size = settings.batch_size
    spec = spec_from_args(args)
    facts = checkpoint_facts(spec)
    pool, executor, dispatchers = build_backend(settings, spec, facts)
    try:
        workers = pool.wait_ready()
        log.info(
            "%s (sha256 %s, profile %s) on %d %s worker(s); batches of up to %d scans, "
            "waiting up to %g ms",
            facts.model,
            facts.sha256[:12],
            facts.profile.name,
            len(workers),
            pool.backend,
            settings.batch_size,
            settings.batch_wait_ms,
        )
        app = create_app(
            settings, pool, executor, facts.profile, facts.sha256, dispatchers, model=facts.model
        )
        uvicorn.run(
            app,
            host=settings.host,
            port=settings.port,
            log_level=args.log_level,
            timeout_graceful_shutdown=30,
            http=GatewayProtocol.with_header_timeout(settings.header_timeout_s),
            limit_concurrency=settings.max_connections,
            root_path=settings.root_path,
        )
    finally:
        pool.shutdown()
    return 0
