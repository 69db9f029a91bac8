"""Container health check: the gateway answers /healthz; on a Ray node the raylet is alive.

The container's role is read from its first process's arguments: the entrypoint's mode, or a
command that runs `ray start`: KubeRay's `/bin/bash -c -- "... ray start ... --block"`, or the
`ray start` itself, which bash runs in its own place as the script's last command
(`.../python3 .../ray start ...` as process 1).
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import urllib.request
from pathlib import Path


def role(cmdline: Path = Path("/proc/1/cmdline")) -> str:
    """`gateway` or `ray` (a head or worker node), from the container's command line."""
    try:
        args = cmdline.read_bytes().decode().split("\0")
    except OSError:
        args = []
    if any(mode in args for mode in ("ray-head", "ray-worker")) or any(
        "ray start" in arg for arg in args
    ):
        return "ray"
    if any(
        Path(arg).name == "ray" and following == "start"
        for arg, following in itertools.pairwise(args)
    ):
        return "ray"
    return "gateway"


def main() -> int:
    """Exit 0 when the process this container runs is healthy."""
    if role() == "gateway":
        port = os.environ.get("RANGERET_PORT", "8000")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as reply:
                return 0 if reply.status == 200 else 1
        except OSError:
            return 1
    return subprocess.run(["ray", "health-check"], check=False, capture_output=True).returncode


if __name__ == "__main__":
    sys.exit(main())
