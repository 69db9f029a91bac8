"""Where a Ray that a run starts for itself keeps its files: its token in the run's own folder
(never `~/.ray/auth_token`, which Ray writes for a new local cluster otherwise), and its session
folder, which stays under /tmp while Ray runs (Ray's socket paths must be short) and is removed
at the end, its logs moved into the run's folder first."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path

#: The variables through which Ray finds or disables its token.
TOKEN_VARIABLES = ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH", "RAY_AUTH_MODE")
#: The token file in a run's Ray folder.
TOKEN_FILE = "auth_token"


@contextlib.contextmanager
def run_token(folder: Path) -> Iterator[Path | None]:
    """Give a local Ray started in the block a token of its own, written to `folder/auth_token`
    (mode 0600) and named by RAY_AUTH_TOKEN_PATH, so that Ray writes none in the home folder;
    the environment is restored after. Yields the file, or None (nothing written) where the
    environment already gives a token or a mode, which are then left to Ray as they are."""
    if any(os.environ.get(name) for name in TOKEN_VARIABLES):
        yield None
        return
    folder.mkdir(parents=True, exist_ok=True)
    path = (folder / TOKEN_FILE).resolve()
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w") as file:
        file.write(secrets.token_hex(32))
    os.environ["RAY_AUTH_TOKEN_PATH"] = str(path)
    _forget_cached_token()
    try:
        yield path
    finally:
        for name in TOKEN_VARIABLES:  # Ray sets RAY_AUTH_MODE itself when it enables tokens
            os.environ.pop(name, None)
        _forget_cached_token()


def keep_logs(session_root: Path, logs: Path, into: Path) -> Path:
    """Move a stopped Ray's log folder `logs` to `into` (replacing an earlier run's) and remove
    its whole session folder `session_root`; the logs' new place."""
    if into.exists():
        shutil.rmtree(into, ignore_errors=True)
    into.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(logs, into, symlinks=True, ignore_dangling_symlinks=True)
    shutil.rmtree(session_root, ignore_errors=True)
    return into


def _forget_cached_token() -> None:
    """Make Ray read its token again (its loader caches the first one it found)."""
    with contextlib.suppress(ImportError, AttributeError):
        from ray._raylet import AuthenticationTokenLoader

        AuthenticationTokenLoader.instance().reset_cache()
