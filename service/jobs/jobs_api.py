"""The Ray Jobs API as the gateway uses it: `JobsApi`, every request bounded in time and every
failure one sentence naming the address (`JobsApiError`, or `JobsApiUnreachable` for one worth
trying again)."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ray.job_submission import JobSubmissionClient

#: Longest one request to the Jobs API may take.
REQUEST_TIMEOUT_S = 10.0
#: Most characters of a dead job's log kept in the failed job's reason.
LOG_TAIL_CHARS = 2000
#: A log line that states an error: a Python exception's last line, or a command's "error:".
_ERROR_LINE = re.compile(r"^(?:[\w.]*(?:Error|Exception|Exit|Interrupt)\b.*|.*\berror: .+)$")


class JobsApiError(Exception):
    """The Jobs API refused a request or gave an answer the gateway cannot use."""


class JobsApiUnreachable(JobsApiError):
    """The Jobs API did not answer (not listening, timed out, or a server error)."""


class JobsApi:
    """The Ray Jobs API at `address` through Ray's own `JobSubmissionClient`, which sends the Ray
    token (RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token) when RAY_AUTH_MODE=token.

    Every request is bounded by `timeout` seconds, and every failure is a `JobsApiError` (or
    `JobsApiUnreachable`) with one sentence that names the address.
    """

    def __init__(self, address: str, timeout: float = REQUEST_TIMEOUT_S) -> None:
        self.address = address
        self.timeout = timeout
        self._client: JobSubmissionClient | None = None

    def status(self, sid: str) -> str | None:
        """The Ray job's status (PENDING, RUNNING, SUCCEEDED, FAILED, STOPPED); None when the
        Jobs API does not know the submission id."""
        try:
            info = self._call(lambda c: c.get_job_info(sid))
        except _NotFound:
            return None
        return str(getattr(info.status, "value", info.status))

    def submit(self, sid: str, entrypoint: str, metadata: dict[str, str]) -> None:
        """Submit `entrypoint` as the Ray job `sid`, with no runtime environment to upload."""
        self._call(
            lambda c: c.submit_job(entrypoint=entrypoint, submission_id=sid, metadata=metadata)
        )

    def stop(self, sid: str) -> bool:
        """Ask the Ray job to stop; False when it had ended or the Jobs API does not know it."""
        try:
            return bool(self._call(lambda c: c.stop_job(sid)))
        except _NotFound:
            return False

    def log_tail(self, sid: str, chars: int = LOG_TAIL_CHARS) -> str:
        """Why the Ray job's log says it ended, on one line ("" when it cannot be read):
        `log_reason` of its log."""
        try:
            text = self._call(lambda c: c.get_job_logs(sid))
        except JobsApiError:
            return ""
        return log_reason(str(text), chars)

    def _connect(self) -> JobSubmissionClient:
        """The client, made on first use (it checks the cluster's Ray version, so it needs the
        Jobs API to answer)."""
        if self._client is None:
            self._client = _bounded_client(self.address, self.timeout)
        return self._client

    def _call(self, request: Callable[[JobSubmissionClient], Any]) -> Any:
        """Run one request, its failures turned into `JobsApiError`s naming the address."""
        from ray.exceptions import AuthenticationError

        try:
            return request(self._connect())
        except AuthenticationError as exc:
            raise JobsApiError(
                f"the Ray Jobs API at {self.address} refused the gateway's Ray token "
                f"({first_line(exc.message)}; set RAY_AUTH_MODE=token and the cluster's token "
                "in RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH)"
            ) from exc
        except OSError as exc:  # requests' errors and the client's ConnectionError
            raise JobsApiUnreachable(
                f"the Ray Jobs API at {self.address} does not answer ({first_line(str(exc))})"
            ) from exc
        except RuntimeError as exc:
            text = first_line(str(exc))
            if "status code 404" in text:
                raise _NotFound(text) from exc
            if "status code 5" in text:
                raise JobsApiUnreachable(
                    f"the Ray Jobs API at {self.address} failed a request ({text})"
                ) from exc
            raise JobsApiError(
                f"the Ray Jobs API at {self.address} refused a request ({text})"
            ) from exc


class _NotFound(JobsApiError):
    """The Jobs API does not know the submission id."""


def _bounded_client(address: str, timeout: float) -> JobSubmissionClient:
    """A `JobSubmissionClient` whose every request gives up after `timeout` seconds (Ray's own
    client waits for ever on a server that accepts the connection and never answers)."""
    from ray.job_submission import JobSubmissionClient

    class BoundedClient(JobSubmissionClient):
        def __init__(self) -> None:
            self._request_timeout = timeout
            super().__init__(address)

        def _do_request(self, method: str, endpoint: str, **kwargs: Any) -> Any:
            kwargs.setdefault("timeout", self._request_timeout)
            return super()._do_request(method, endpoint, **kwargs)

    return BoundedClient()


def first_line(text: str) -> str:
    """The first non-empty line of `text`, whitespace collapsed and cut to 300 characters."""
    for line in text.splitlines():
        if line.strip():
            return " ".join(line.split())[:300].rstrip(".")
    return "no details"


def log_reason(text: str, chars: int = LOG_TAIL_CHARS) -> str:
    """The reason a log gives for a failure, on one line: its last error line (a Python
    exception's, a command's `error:`) whole, with what follows it, since Ray's and the
    interpreter's closing lines come after the error; else its last three lines. At most `chars`
    characters, cut at the end, never at the start where the error is."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    errors = [i for i, line in enumerate(lines) if _ERROR_LINE.match(line)]
    kept = lines[errors[-1] :] if errors else lines[-3:]
    reason = " | ".join(kept)
    return reason if len(reason) <= chars else reason[: chars - 3].rstrip() + "..."
