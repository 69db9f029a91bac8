"""Paths given to a Ray job's entrypoint, checked where the job runs.

`ray job submit --working-dir .` uploads the folder and runs the entrypoint in the job's copy of
it, so a relative path names a file in that copy, not the one the user typed it beside: an input
there is missing, and an output there is lost with the copy. Such a path is one line saying so.
A job that was not given an uploaded working directory (or a plain local run) takes relative
paths as they are.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

from rangeret.commands import CommandError

#: Where Ray hands a job's driver its runtime environment.
JOB_CONFIG_VARIABLE = "RAY_JOB_CONFIG_JSON_ENV_VAR"


def uploaded_working_dir() -> bool:
    """Whether this process is a Ray job's driver run in an uploaded working directory."""
    try:
        config = json.loads(os.environ.get(JOB_CONFIG_VARIABLE) or "{}")
    except ValueError:
        return False
    runtime_env = config.get("runtime_env") if isinstance(config, dict) else None
    return isinstance(runtime_env, dict) and bool(runtime_env.get("working_dir"))


def check_job_paths(
    inputs: Iterable[tuple[str, Path | None]], outputs: Iterable[tuple[str, Path | None]]
) -> None:
    """In an uploaded working directory, a relative input that is not in the job's copy, or any
    relative output, is a `CommandError` naming the option; elsewhere nothing is checked."""
    if not uploaded_working_dir():
        return
    for option, path in inputs:
        if path is not None and not path.is_absolute() and not path.exists():
            raise CommandError(
                f"{option} {path} is relative, and this Ray job runs in its copy of the uploaded "
                f"working directory ({Path.cwd()}), which does not hold it: pass an absolute path "
                "that every node can read"
            )
    for option, path in outputs:
        if path is not None and not path.is_absolute():
            raise CommandError(
                f"{option} {path} is relative, and this Ray job runs in its copy of the uploaded "
                "working directory, where what it writes is lost with the copy: pass an absolute "
                "path on storage every node mounts"
            )
