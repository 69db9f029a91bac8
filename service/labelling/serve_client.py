"""Single scans labelled by the Serve application (`workers.serve_app`) through Serve's HTTP proxy.

`ServeLabeller` posts each admitted scan's point records to `<serve url>/scans` (the proxy's scheme, host
and port, then the application's route prefix) with the scan's model in Serve's
`serve_multiplexed_model_id` header, and reads the labels back in the exchange of
`workers.scan_wire`; Serve routes each request to a replica that has its model loaded and batches
concurrent requests of one model there. An answer that does not
come within `timeout` seconds is `BackendTimeout` (504); an unreachable, overloaded (503) or
failing application is `BackendError` (503 with Retry-After). At start-up `check_serves` compares
every model's checkpoint and profile with the application's model of the same name.
"""

from __future__ import annotations

import asyncio
import logging
import time

import httpx
import numpy as np

from rangeret.commands import CommandError
from rangeret.inference.results import ScanPrediction
from service.labelling.errors import BackendError, BackendTimeout, ScanRejected
from service.models.catalog import ModelCatalog
from workers.scan_wire import INFO_PATH, OCTET, SCANS_PATH, decode_labels, options_query

log = logging.getLogger(__name__)

#: Connections kept open to the proxy; requests beyond them wait for one (within `timeout`).
MAX_CONNECTIONS = 256
#: How long one health or start-up probe of the application may take.
PROBE_TIMEOUT_S = 10.0
#: The header that names a request's model to Serve's multiplexing.
MODEL_ID_HEADER = "serve_multiplexed_model_id"


class ServeLabeller:
    """Labels single scans on the Serve application at `url`."""

    backend = "serve"

    def __init__(self, url: str, models: ModelCatalog, timeout: float) -> None:
        self.url = url.rstrip("/")
        self.models = models
        self.timeout = timeout
        self._client: httpx.AsyncClient | None = None
        self._in_flight = 0

    def _new_client(self) -> httpx.AsyncClient:
        limits = httpx.Limits(
            max_connections=MAX_CONNECTIONS, max_keepalive_connections=MAX_CONNECTIONS
        )
        return httpx.AsyncClient(timeout=httpx.Timeout(self.timeout), limits=limits)

    async def start(self, on_batch: object = None) -> None:
        """Open the connection pool (Serve does the batching, so `on_batch` is not called)."""
        self._client = self._new_client()

    async def stop(self) -> None:
        """Close the connection pool."""
        if self._client is not None:
            await self._client.aclose()
            self._client = None

    async def label_points(
        self,
        points: np.ndarray,
        knn: bool = True,
        confidence: bool = False,
        panoptic: bool = False,
        *,
        model: str,
    ) -> ScanPrediction:
        """One scan labelled by the application's model `model`, sent as its point records'
        bytes (with `panoptic`, with its objects)."""
        if self._client is None:
            raise BackendError("the gateway is starting; try again in a moment")
        self._in_flight += 1
        try:
            response = await asyncio.wait_for(
                self._client.post(
                    self.url + SCANS_PATH,
                    params=options_query(knn, confidence, panoptic),
                    content=np.ascontiguousarray(points, dtype="<f4").tobytes(),
                    headers={"Content-Type": OCTET, MODEL_ID_HEADER: model},
                ),
                self.timeout,
            )
        except (asyncio.TimeoutError, httpx.TimeoutException) as exc:
            raise BackendTimeout(
                f"the Serve application at {self.url} did not answer within {self.timeout:g} s "
                "(RANGERET_SERVE_TIMEOUT_S)"
            ) from exc
        except httpx.TransportError as exc:
            raise BackendError(
                f"the Serve application at {self.url} cannot be reached ({_reason(exc)})"
            ) from exc
        finally:
            self._in_flight -= 1
        labelled = self._answer(response, len(points))
        if panoptic and labelled.instances is None:
            raise BackendError(
                f"the Serve application at {self.url} answered a panoptic request without the "
                "scan's objects: deploy an application that finds them"
            )
        return labelled

    def _answer(self, response: httpx.Response, points: int) -> ScanPrediction:
        """The labels of a 200, or the error its status means."""
        if response.status_code == 200:
            try:
                return decode_labels(response.content, response.headers, points)
            except ValueError as exc:
                raise BackendError(str(exc)) from exc
        detail = _detail(response)
        if response.status_code == 422:
            raise ScanRejected(detail.removeprefix("The scan cannot be projected: ").rstrip("."))
        if response.status_code in (408, 504):
            raise BackendTimeout(
                f"the Serve application at {self.url} timed out ({response.status_code})"
            )
        if response.status_code == 503:
            raise BackendError(
                f"the Serve application at {self.url} is overloaded or has no replica ready"
            )
        if response.status_code == 404 and detail.startswith("There is no model"):
            raise BackendError(f"the Serve application at {self.url}: {detail.rstrip('.')}")
        if response.status_code == 404:
            raise BackendError(
                f"no Serve application answers at {self.url} (404): is it deployed with this "
                "route prefix?"
            )
        raise BackendError(
            f"the Serve application at {self.url} answered {response.status_code}: {detail}"
        )

    def depth(self) -> int:
        """Scans sent to the application and not answered yet."""
        return self._in_flight

    def loaded(self) -> None:
        """None: the application loads and unloads the networks itself."""
        return None

    async def health(self) -> dict:
        """Whether the application answers, and what it serves."""
        client = self._client or self._new_client()
        try:
            response = await client.get(self.url + INFO_PATH, timeout=PROBE_TIMEOUT_S)
            response.raise_for_status()
            return {"backend": self.backend, "ok": True, "workers": [response.json()]}
        except (httpx.HTTPError, ValueError) as exc:
            return {
                "backend": self.backend,
                "ok": False,
                "error": f"the Serve application at {self.url}: {_reason(exc)}",
            }
        finally:
            if client is not self._client:
                await client.aclose()

    def check_serves(self, wait_s: float) -> dict:
        """The application's description, once it answers (waiting up to `wait_s` seconds);
        a `CommandError` naming the model when the application lacks one of the gateway's
        models or serves it with another checkpoint or profile, or when it never answers."""
        deadline = time.monotonic() + wait_s
        problem = ""
        while True:
            try:
                response = httpx.get(self.url + INFO_PATH, timeout=PROBE_TIMEOUT_S)
                if response.status_code == 200:
                    served = response.json()
                    break
                problem = f"it answered {response.status_code}"
            except (httpx.HTTPError, ValueError) as exc:
                problem = _reason(exc)
            if time.monotonic() >= deadline:
                raise CommandError(
                    f"the Serve application at {self.url} did not answer within {wait_s:g} s "
                    f"({problem}): deploy it first (serve deploy, or the RayService), or fix "
                    "--serve-url"
                )
            log.info("waiting for the Serve application at %s (%s)", self.url, problem)
            time.sleep(2.0)
        theirs = {m.get("id"): m for m in served.get("models") or [] if isinstance(m, dict)}
        for entry in self.models:
            model = theirs.get(entry.name)
            named = "" if len(self.models) == 1 else f" for model {entry.name}"
            if model is None:
                raise CommandError(
                    f"the Serve application at {self.url} serves no model {entry.name} (it serves "
                    f"{', '.join(map(str, theirs)) or 'none'}): deploy it with the gateway's "
                    "models file"
                )
            if model.get("checkpoint_sha256") != entry.checkpoint_sha256:
                raise CommandError(
                    f"the Serve application at {self.url} serves checkpoint sha256 "
                    f"{model.get('checkpoint_sha256')}{named} and this gateway's checkpoint is "
                    f"sha256 {entry.checkpoint_sha256}: give both the same weights"
                )
            if model.get("profile") != entry.profile.name:
                raise CommandError(
                    f"the Serve application at {self.url} serves the {model.get('profile')} "
                    f"profile{named} and this gateway the {entry.profile.name} profile: give both "
                    "the same one"
                )
        return served


def _detail(response: httpx.Response) -> str:
    """The `detail` of an error answer, or the start of its text."""
    try:
        return str(response.json()["detail"])
    except (ValueError, KeyError, TypeError):
        return " ".join(response.text.split())[:200] or response.reason_phrase


def _reason(exc: BaseException) -> str:
    """A short reason for a failed request."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}"[:300] if text else type(exc).__name__
