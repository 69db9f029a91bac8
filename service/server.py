"""`rangeret serve`: build the single-scan labeller and the job executor, then run the gateway on
uvicorn.

On a cluster, single scans go to the Serve application at `--serve-url` (RANGERET_SERVE_URL,
`workers.serve_app`) and jobs become Ray jobs through the Jobs API at `--jobs-address`
(RANGERET_JOBS_ADDRESS); without them, each runs in this process (`LocalLabeller`,
`predict_tree`) on one network: the checkpoint is read once, and single scans and job batches
take turns on the network, one pass at a time. Options given on the command line win over
RANGERET_* variables. The gateway serves one dataset profile: the checkpoint's, or the one given
with `--profile`.
"""

from __future__ import annotations

import argparse
import logging
import os
from typing import TYPE_CHECKING

from pydantic import ValidationError

from rangeret.commands import CommandError
from rangeret.extras import require_extra
from rangeret.inference.spec import InferenceSpec
from rangeret.options import add_network_options
from service.errors import validation_sentence
from service.gateway import ScanLabeller
from service.jobs import JobExecutor
from service.settings import Settings

if TYPE_CHECKING:  # torch is imported when the gateway starts, not to build its parser
    from rangeret.inference.loader import LoadedWeights
    from rangeret.inference.predictor import Predictor

log = logging.getLogger("rangeret.serve")

#: Options of `serve` that override the settings of the same name.
_OVERRIDES = (
    "host",
    "port",
    "batch_size",
    "batch_wait_ms",
    "serve_url",
    "serve_timeout_s",
    "jobs_address",
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
        "--serve-url",
        metavar="URL",
        help="the Serve application that labels single scans: the proxy's http://host:port "
        "followed by the application's route prefix (default: the network runs in this process)",
    )
    g.add_argument(
        "--serve-timeout-s",
        type=float,
        metavar="S",
        help="longest a single scan waits for the Serve application before a 504 (default 300)",
    )
    g.add_argument(
        "--jobs-address",
        metavar="URL",
        help="the Ray dashboard (http://host:8265) whose Jobs API runs the gateway's jobs as Ray "
        "jobs (default: jobs run in this process)",
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


def build_labeller(
    settings: Settings, weights: LoadedWeights, predictor: Predictor | None
) -> ScanLabeller:
    """What labels single scans: the Serve application at `serve_url` (once it answers with the
    same checkpoint and profile), or else `predictor` in this process behind the local batcher."""
    if settings.serve_url:
        from service.serve_client import ServeLabeller

        labeller = ServeLabeller(settings.serve_url, weights.profile, settings.serve_timeout_s)
        labeller.check_serves(weights.sha256 or "", settings.serve_timeout_s)
        return labeller
    from rangeret.inference.scan_worker import ScanWorker, use_cpus
    from service.local_labeller import LocalLabeller

    assert predictor is not None  # `run_serve` builds one whenever a part runs in this process
    use_cpus(float(os.cpu_count() or 1))  # the network has the gateway's machine to itself
    return LocalLabeller(ScanWorker(predictor), settings.batch_size, settings.batch_wait_ms / 1000)


def build_executor(
    settings: Settings, spec: InferenceSpec, weights: LoadedWeights, predictor: Predictor | None
) -> JobExecutor:
    """What runs the gateway's jobs: Ray jobs through the Jobs API at `jobs_address` (the same
    entrypoint as `ray job submit`, given the gateway's spec), or else `predict_tree` in this
    process with `predictor`, the network single scans share."""
    from service.jobs import LocalExecutor

    roots = [*settings.data_roots, settings.jobs_folder.resolve()]  # checked again at read time
    if settings.jobs_address:
        from service.jobs.ray_jobs import RayJobExecutor

        return RayJobExecutor(settings.jobs_address, spec, weights.profile, read_roots=roots)
    assert predictor is not None  # `run_serve` builds one whenever a part runs in this process
    return LocalExecutor(predictor, spec.batch_size, read_roots=roots)


def check_state(settings: Settings) -> None:
    """The state folder, the jobs folder and the job database can be used; else a `CommandError`
    naming the path and the problem in one sentence."""
    from service.jobs import JobDatabaseError, check_job_database

    try:
        settings.jobs_folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CommandError(
            f"cannot use the jobs folder {settings.jobs_folder} (RANGERET_STATE_DIR or "
            f"RANGERET_JOBS_DIR): {exc.strerror or exc}"
        ) from exc
    try:
        check_job_database(settings.database_path)
    except JobDatabaseError as exc:
        raise CommandError(str(exc)) from exc


def run_serve(args: argparse.Namespace) -> int:
    """Run the gateway until it is stopped (Ctrl-C or SIGTERM); returns the exit code."""
    import uvicorn

    from rangeret.inference.loader import load_weights
    from rangeret.inference.predictor import Predictor
    from service.app import create_app
    from service.protocols import GatewayProtocol

    settings = settings_from_args(args)
    problem = settings.address_problem()
    if problem:
        raise CommandError(problem)
    if settings.jobs_address:
        require_extra("rangeret serve --jobs-address", "ray")  # Ray jobs go through Ray's client
    check_state(settings)  # before minutes of loading weights
    args.batch_size = settings.batch_size
    spec = InferenceSpec.from_args(args)
    weights = load_weights(spec)
    if weights.profile.layout.kind == "tables":
        raise CommandError(
            f"rangeret serve takes profiles of folder layouts; the {weights.profile.name} profile "
            "reads a version's tables, which the gateway does not serve: use rangeret predict or "
            "python -m workers.predict_job for it"
        )
    if spec.backend == "onnxruntime":
        weights.export_onnx()  # once here, so that workers started next load it from the cache
    in_process = not (settings.serve_url and settings.jobs_address)
    predictor = Predictor(weights, spec) if in_process else None
    labeller = build_labeller(settings, weights, predictor)
    executor = build_executor(settings, spec, weights, predictor)
    log.info(
        "%s (sha256 %s, profile %s): single scans %s, jobs %s; batches of up to %d scans",
        weights.model,
        (weights.sha256 or "")[:12],
        weights.profile.name,
        f"on the Serve application at {settings.serve_url}"
        if settings.serve_url
        else "in this process",
        f"as Ray jobs at {settings.jobs_address}" if settings.jobs_address else "in this process",
        settings.batch_size,
    )
    app = create_app(
        settings,
        labeller,
        executor,
        profile=weights.profile,
        checkpoint_sha256=weights.sha256,
        model=weights.model,
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
    return 0
