"""`rangeret serve`: check the models, build the single-scan labeller and the job executor, then
run the gateway on uvicorn.

On a cluster, single scans go to the Serve application at `--serve-url` (RANGERET_SERVE_URL,
`workers.serve_app`) and jobs become Ray jobs through the Jobs API at `--jobs-address`
(RANGERET_JOBS_ADDRESS); without them, each runs in this process (`ScanBatcher`,
`predict_tree`) on the networks of the gateway's pool (`ModelPool`): a model's single scans and
job batches take turns on its one network, one pass at a time. Options given on the command line
win over RANGERET_* variables. With `--models` (RANGERET_MODELS) it serves several networks by
name, each with its own profile; a plain `--checkpoint` is the one model `default`. Every
model's checkpoint is checked at start, but only the networks the pool keeps are built: at most
`--max-loaded` (the default model first), the others loaded on first use, the least recently
used one that nothing holds evicted and freed first, so the process holds at most `--max-loaded`
networks. A model loaded at start reads its checkpoint once.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import ValidationError

from rangeret.commands import CommandError
from rangeret.extras import require_extra
from rangeret.inference.spec import InferenceSpec
from rangeret.options import add_network_options
from service.gateway import ScanLabeller
from service.http.errors import validation_sentence
from service.jobs import JobExecutor
from service.settings import Settings

if TYPE_CHECKING:  # torch is imported when the gateway starts, not to build its parser
    from rangeret.inference.model_set import ModelSet
    from service.labelling.pooled import ModelRuntime
    from service.models.catalog import ModelCatalog
    from service.models.loader import ModelLoader
    from service.models.pool import ModelPool

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
    "models",
    "max_loaded",
)
#: Network options a models file names per model, so not beside `--models`.
_PER_MODEL = ("checkpoint", "model")


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
        "--models",
        type=Path,
        metavar="MODELS.yaml",
        help="serve several networks by name: a models file (`default:` and `models:` mapping "
        "each name to its network options); the other network options given here are defaults "
        "an entry overrides (RANGERET_MODELS; not with --checkpoint or --model)",
    )
    g.add_argument(
        "--max-loaded",
        type=int,
        metavar="N",
        help="most networks loaded at once in this process, the least recently used one that "
        "no job holds unloaded first (RANGERET_MAX_LOADED; default: every model)",
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


def model_set(args: argparse.Namespace, settings: Settings) -> ModelSet:
    """The models to serve: the models file's (`--models`, RANGERET_MODELS) over the command
    line's other network options, or the one model `default` of those options."""
    from rangeret.inference.model_set import ModelSet, ModelsFileError, load_models_file

    spec = InferenceSpec.from_args(args)
    if settings.models is None:
        return ModelSet.single(spec)
    given = [name for name in _PER_MODEL if getattr(args, name, None) is not None]
    if given:
        raise CommandError(
            f"--models names each model's checkpoint and network; give --{given[0]} in the "
            f"models file {settings.models}, not beside it"
        )
    try:
        return load_models_file(settings.models, spec)
    except ModelsFileError as exc:
        raise CommandError(str(exc)) from exc


def check_models(loader: ModelLoader, pool: ModelPool[ModelRuntime] | None) -> ModelCatalog:
    """The catalog of the loader's models, each checked once (checkpoint, pin, profile, class
    count), the default first: those the pool has room for are loaded into it from that one read,
    the others identified without building their network (`ModelLoader.check`); a `CommandError`
    naming the model for one a gateway cannot serve."""
    from rangeret.exceptions import RangeRetError
    from service.models.catalog import ModelCatalog

    models = loader.models
    for name in [models.default, *(n for n in models.names if n != models.default)]:
        try:
            loader.check(name, pool)
        except RangeRetError as exc:
            if len(models) == 1:
                raise
            raise CommandError(f"model {name}: {exc}") from exc
    return ModelCatalog.identified(models, loader.identities)


def build_pool(settings: Settings, loader: ModelLoader) -> ModelPool[ModelRuntime]:
    """The pool of networks loaded in this process, at most `max_loaded`, each loaded by
    `loader` on first use (and again after its eviction)."""
    from rangeret.inference.scan_worker import use_cpus
    from service.models.pool import ModelPool

    use_cpus(float(os.cpu_count() or 1))  # the networks have the gateway's machine to themselves
    return ModelPool(loader.models.names, loader, max_loaded=settings.max_loaded)


def build_labeller(
    settings: Settings, catalog: ModelCatalog, pool: ModelPool[ModelRuntime] | None
) -> ScanLabeller:
    """What labels single scans: the Serve application at `serve_url` (once it answers with the
    same checkpoint and profile for every model), or else the pool's networks in this process, each behind its
    own batcher."""
    if settings.serve_url:
        from service.labelling.serve_client import ServeLabeller

        labeller = ServeLabeller(settings.serve_url, catalog, settings.serve_timeout_s)
        labeller.check_serves(settings.serve_timeout_s)
        return labeller
    from service.labelling.pooled import PooledLabeller

    assert pool is not None  # `run_serve` builds one whenever a part runs in this process
    return PooledLabeller(pool)


def build_executor(
    settings: Settings, catalog: ModelCatalog, pool: ModelPool[ModelRuntime] | None
) -> JobExecutor:
    """What runs the gateway's jobs: Ray jobs through the Jobs API at `jobs_address` (the same
    entrypoint as `ray job submit`, given the model's spec), or else `predict_tree` in this
    process with the job's model from the pool, the networks single scans share."""
    from service.jobs import LocalExecutor

    roots = [*settings.data_roots, settings.jobs_folder.resolve()]  # checked again at read time
    if settings.jobs_address:
        from service.jobs.ray_jobs import RayJobExecutor

        return RayJobExecutor(settings.jobs_address, catalog, read_roots=roots)
    assert pool is not None  # `run_serve` builds one whenever a part runs in this process
    return LocalExecutor(pool, catalog.default, settings.batch_size, read_roots=roots)


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

    from service.app import create_app
    from service.http.protocols import GatewayProtocol
    from service.models.loader import ModelLoader

    logging.getLogger("httpx").setLevel(logging.WARNING)  # no line per request to Serve
    settings = settings_from_args(args)
    problem = settings.address_problem()
    if problem:
        raise CommandError(problem)
    if settings.jobs_address:
        require_extra("rangeret serve --jobs-address", "ray")  # Ray jobs go through Ray's client
    check_state(settings)  # before minutes of loading weights
    args.batch_size = settings.batch_size
    models = model_set(args, settings)
    loader = ModelLoader(models, settings.batch_size, settings.batch_wait_ms / 1000)
    in_process = not (settings.serve_url and settings.jobs_address)
    pool = build_pool(settings, loader) if in_process else None
    catalog = check_models(loader, pool)
    labeller = build_labeller(settings, catalog, pool)
    executor = build_executor(settings, catalog, pool)
    for entry in catalog:
        log.info(
            "model %s: %s (sha256 %s, profile %s)",
            entry.name,
            entry.network,
            (entry.checkpoint_sha256 or "")[:12],
            entry.profile.name,
        )
    log.info(
        "default model %s; single scans %s, jobs %s; batches of up to %d scans%s",
        catalog.default,
        f"on the Serve application at {settings.serve_url}"
        if settings.serve_url
        else "in this process",
        f"as Ray jobs at {settings.jobs_address}" if settings.jobs_address else "in this process",
        settings.batch_size,
        f"; at most {pool.max_loaded} of {len(catalog)} networks loaded at once"
        if pool is not None and len(catalog) > 1
        else "",
    )
    app = create_app(settings, labeller, executor, models=catalog)
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
