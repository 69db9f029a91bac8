"""Gateway settings from the environment (`RANGERET_*`), overridable by `rangeret serve` options.

RANGERET_HOST              address to listen on (default 127.0.0.1; another needs a token)
RANGERET_PORT              port to listen on (default 8000)
RANGERET_API_TOKEN         bearer token every /v1 request must carry (unset: loopback only)
RANGERET_DATA_ROOTS        folders, separated by ':' (or a JSON list), that dataset jobs may read
RANGERET_STATE_DIR         where job folders and the job database live (default runs/gateway)
RANGERET_JOBS_DIR          job folders (default STATE_DIR/jobs)
RANGERET_DATABASE          the SQLite job database (default STATE_DIR/jobs.sqlite)
RANGERET_RETENTION         seconds (or ISO 8601) a finished job's files are kept (default 1 day)
RANGERET_MAX_BODY_BYTES    largest single-scan or JSON request body (default 64 MiB)
RANGERET_MAX_POINTS        most points per scan (default 2,000,000)
RANGERET_MAX_DECODED_BYTES most bytes a PCD, PLY or LAS/LAZ body may decode to: its declared points
                           times the wider of its point and the profile's record, checked from
                           its header before anything is allocated (default 256 MiB)
RANGERET_MAX_ARCHIVE_BYTES largest archive upload (default 4 GiB)
RANGERET_MAX_EXTRACTED_BYTES largest total of an archive's files once extracted (default 16 GiB)
RANGERET_MAX_ARCHIVE_MEMBERS most entries per archive, folders included (default 100,000)
RANGERET_MAX_QUEUED_SCANS  most single-scan requests admitted and not yet answered (default 128)
RANGERET_MAX_QUEUED_BYTES  most body bytes of those requests (default 1 GiB)
RANGERET_HEADER_TIMEOUT_S  longest a request line and headers may take to arrive (default 10)
RANGERET_BODY_TIMEOUT_S    longest a single-scan or JSON body may take to arrive (default 60)
RANGERET_UPLOAD_TIMEOUT_S  longest an archive upload may take to arrive (default 3600)
RANGERET_MAX_CONNECTIONS   most open connections; beyond, 503 (default 1000)
RANGERET_MAX_RUNNING_JOBS  jobs run at once (default 2)
RANGERET_MAX_QUEUED_JOBS   most jobs waiting to run; beyond, 429 (default 100)
RANGERET_MAX_JOB_BYTES     most disk the job folders may use together; beyond, 507 (default 100 GiB)
RANGERET_BATCH_SIZE        most single-scan requests per network pass (default 1)
RANGERET_BATCH_WAIT_MS     longest a request waits for others to fill its batch (default 10)
RANGERET_SERVE_URL         the Serve application that labels single scans (proxy URL and route
                           prefix, e.g. http://rangeret-serve-svc:8000/rangeret); unset: in-process
RANGERET_SERVE_TIMEOUT_S   longest a single scan may wait for the Serve application (default 300)
RANGERET_JOBS_ADDRESS      the Ray dashboard whose Jobs API runs the gateway's jobs
                           (e.g. http://rangeret-head-svc:8265); unset: jobs run in-process
RANGERET_MODELS            a models file (YAML): several networks by name, and the default one
RANGERET_MAX_LOADED        most networks loaded at once in this process (default: every model)
RANGERET_ROOT_PATH         path prefix a reverse proxy serves the gateway under (e.g. /rangeret)
RANGERET_ALLOWED_HOSTS     Host names the gateway answers to, separated by ','; default: any with a
                           token, the loopback names and the bound address without one

docs/http-api.md describes every setting with the endpoints and answers it shapes.
"""

from __future__ import annotations

import ipaddress
import json
import os
from datetime import timedelta
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from rangeret.io.decode_limits import DEFAULT_MAX_DECODED_BYTES
from service.http.origins import default_allowed_hosts

MIB = 1 << 20
GIB = 1 << 30


class Settings(BaseSettings):
    """Everything the gateway needs besides the network options: address, token, storage, limits."""

    model_config = SettingsConfigDict(env_prefix="RANGERET_", extra="ignore", frozen=True)

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)
    api_token: SecretStr | None = None
    data_roots: Annotated[list[Path], NoDecode] = Field(default_factory=list)
    state_dir: Path = Path("runs/gateway")
    jobs_dir: Path | None = None
    database: Path | None = None
    retention: timedelta = Field(default=timedelta(days=1), gt=timedelta(0))
    max_body_bytes: int = Field(default=64 * MIB, gt=0)
    max_points: int = Field(default=2_000_000, gt=0)
    max_decoded_bytes: int = Field(default=DEFAULT_MAX_DECODED_BYTES, gt=0)
    max_archive_bytes: int = Field(default=4 * GIB, gt=0)
    max_extracted_bytes: int = Field(default=16 * GIB, gt=0)
    max_archive_members: int = Field(default=100_000, gt=0)
    max_queued_scans: int = Field(default=128, gt=0)
    max_queued_bytes: int = Field(default=1 * GIB, gt=0)
    header_timeout_s: float = Field(default=10.0, gt=0)
    body_timeout_s: float = Field(default=60.0, gt=0)
    upload_timeout_s: float = Field(default=3600.0, gt=0)
    max_connections: int = Field(default=1000, gt=0)
    max_running_jobs: int = Field(default=2, ge=1)
    max_queued_jobs: int = Field(default=100, ge=1)
    max_job_bytes: int = Field(default=100 * GIB, gt=0)
    batch_size: int = Field(default=1, ge=1)
    batch_wait_ms: float = Field(default=10.0, ge=0)
    serve_url: str | None = None
    serve_timeout_s: float = Field(default=300.0, gt=0)
    jobs_address: str | None = None
    models: Path | None = None
    max_loaded: int | None = Field(default=None, ge=1)
    root_path: str = ""
    allowed_hosts: Annotated[list[str] | None, NoDecode] = None

    @field_validator("allowed_hosts", mode="before")
    @classmethod
    def _split_hosts(cls, value: object) -> object:
        """Accept `a,b` (or a JSON list) as well as a list; empty counts as unset."""
        return _split_list(value, ",") or None

    @field_validator("data_roots", mode="before")
    @classmethod
    def _split_roots(cls, value: object) -> object:
        """Accept `a:b` (os.pathsep-separated) or a JSON list, as well as a list."""
        return _split_list(value, os.pathsep)

    @field_validator("retention", mode="before")
    @classmethod
    def _seconds(cls, value: object) -> object:
        """A plain number of seconds, as well as an ISO 8601 duration."""
        if isinstance(value, str):
            try:
                return timedelta(seconds=float(value))
            except ValueError:
                return value
        return value

    @field_validator(
        "api_token", "serve_url", "jobs_address", "models", "max_loaded", mode="before"
    )
    @classmethod
    def _empty_is_unset(cls, value: object) -> object:
        """An empty variable counts as unset, so `RANGERET_API_TOKEN=` never means an empty token."""
        if isinstance(value, str) and not value.strip():
            return None
        return value

    @field_validator("serve_url", "jobs_address", mode="after")
    @classmethod
    def _http_url(cls, value: str | None) -> str | None:
        """An http(s) URL with a host, kept without a trailing `/`."""
        if value is None:
            return None
        text = value.strip().rstrip("/")
        scheme, _, rest = text.partition("://")
        if scheme not in ("http", "https") or not rest or rest.startswith("/"):
            raise ValueError(f"an http:// or https:// URL with a host, got {value!r}")
        return text

    @field_validator("root_path", mode="after")
    @classmethod
    def _prefix(cls, value: str) -> str:
        """A path prefix such as `/rangeret`: empty, or `/` then path segments, no trailing `/`."""
        text = value.strip().rstrip("/")
        if text and (not text.startswith("/") or any(c in text for c in "?#\\ ")):
            raise ValueError(
                f"a path prefix starts with '/' and holds no '?', '#', '\\' or space, got {value!r}"
            )
        return text

    @field_validator("data_roots", mode="after")
    @classmethod
    def _resolved_roots(cls, value: list[Path]) -> list[Path]:
        """Data roots are compared after resolving links, so keep them resolved."""
        return [p.expanduser().resolve() for p in value]

    @property
    def jobs_folder(self) -> Path:
        """Folder holding one sub-folder per job."""
        return self.jobs_dir or self.state_dir / "jobs"

    @property
    def database_path(self) -> Path:
        """The SQLite file holding the job records."""
        return self.database or self.state_dir / "jobs.sqlite"

    def host_allow_list(self) -> list[str] | None:
        """The Host names the gateway answers to (None: any): `allowed_hosts` where set, else
        the loopback names and the bound address on a gateway without a token."""
        if self.allowed_hosts:
            return list(self.allowed_hosts)
        return None if self.token else list(default_allowed_hosts(self.host))

    @property
    def token(self) -> str | None:
        """The bearer token in clear, or None when the gateway runs without one."""
        return self.api_token.get_secret_value() if self.api_token else None

    def address_problem(self) -> str | None:
        """Why the token rule forbids serving on `host`, or None when it may serve there."""
        if self.token or is_loopback(self.host):
            return None
        return (
            f"refusing to serve on {self.host} without RANGERET_API_TOKEN: without a token the "
            "gateway serves only on a loopback address such as 127.0.0.1"
        )


def _split_list(value: object, separator: str) -> object:
    """A variable's list: a JSON list, or items between `separator`s (blank ones dropped); any
    other value as it is."""
    if not isinstance(value, str):
        return value
    text = value.strip()
    if text.startswith("["):
        return json.loads(text)
    return [part.strip() for part in text.split(separator) if part.strip()]


def is_loopback(host: str) -> bool:
    """Whether `host` is a loopback address (127.0.0.0/8, ::1) or the name localhost."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False
