"""Counting, per process, the reads of a checkpoint file and the imports of `workers` modules
in processes a test starts (the audit hook of `tests/support/audit/sitecustomize.py`)."""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

AUDIT_DIR = Path(__file__).parent / "audit"


@dataclass(frozen=True)
class Audit:
    """Where a run's audit lines go, and the file names whose reads count."""

    log: Path
    names: tuple[str, ...]

    def env(self, base: dict[str, str] | None = None) -> dict[str, str]:
        """`base` (default: this process's environment) with the audit hook switched on."""
        env = dict(os.environ if base is None else base)
        path = env.get("PYTHONPATH")
        env["PYTHONPATH"] = str(AUDIT_DIR) + (os.pathsep + path if path else "")
        env["RANGERET_TEST_AUDIT_LOG"] = str(self.log)
        env["RANGERET_TEST_AUDIT_FILES"] = ",".join(self.names)
        return env

    def lines(self) -> list[tuple[int, str, str]]:
        """(pid, kind, what) of every line so far."""
        if not self.log.exists():
            return []
        found = []
        for line in self.log.read_text().splitlines():
            pid, kind, what = line.split(" ", 2)
            found.append((int(pid), kind, what))
        return found

    def reads(self) -> Counter[int]:
        """How often each process read a watched file."""
        return Counter(pid for pid, kind, _ in self.lines() if kind == "read")

    def imports(self, pid: int) -> list[str]:
        """The `workers` modules process `pid` imported."""
        return [what for p, kind, what in self.lines() if p == pid and kind == "import"]
