"""Peak memory of a process, for the tests that bound it: a child command's peak resident set
(`wait4`'s rusage, that child's alone), and the peak of a running process since a reset of its
high-water mark (`/proc/PID/clear_refs`, then `VmHWM` in `/proc/PID/status`)."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

KIB = 1024


@dataclass(frozen=True)
class Finished:
    """A command's exit code, output and peak resident set (bytes)."""

    returncode: int
    stdout: str
    stderr: str
    peak_bytes: int


def run_measured(argv: Sequence[str], *, env: dict[str, str], cwd: Path, log: Path) -> Finished:
    """Run `argv` to its end; its exit code, output and peak resident set (its own, not that of
    other children of this process)."""
    out, err = log.with_suffix(".out"), log.with_suffix(".err")
    with open(out, "wb") as stdout, open(err, "wb") as stderr:
        proc = subprocess.Popen(argv, env=env, cwd=cwd, stdout=stdout, stderr=stderr)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return Finished(
        proc.returncode,
        out.read_text(errors="replace"),
        err.read_text(errors="replace"),
        usage.ru_maxrss * KIB,
    )


def status_bytes(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of process `pid`, in bytes."""
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0]) * KIB
    return values


def reset_peak(pid: int) -> bool:
    """Set process `pid`'s peak resident set to its current one; False where the kernel does
    not allow it."""
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    except OSError:
        return False
    values = status_bytes(pid)
    return values["VmHWM"] <= values["VmRSS"] + 4 * KIB * KIB


def peak_growth(pid: int, since: int) -> int:
    """How far process `pid`'s peak resident set rose above `since` bytes."""
    return status_bytes(pid)["VmHWM"] - since
