"""The commands a page of the documentation shows in its code blocks, and the options that keep
their runs small on a CPU, shared by the tests that run a page's commands as written."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

#: A one-block network of width 16: one training step takes a second on a CPU.
SMALL_NET = ["--override", "layers=1", "--override", "heads=2", "--override", "dim=16"]
#: What keeps a training run to one step on this machine.
ONE_STEP = ["--epochs", "1", "--max-steps", "1", "--loader-workers", "0", "--device", "cpu"]


def code_commands(
    text: str, prefixes: tuple[str, ...] = ("rangeret ",), language: str | None = None
) -> list[str]:
    """The lines of a page's code blocks (of `language` only, when given) that start with one of
    `prefixes`, continuation lines joined and trailing `# ...` comments removed, in order; blocks
    written after a `$` prompt show outputs, not steps, and are left out."""
    fence = "[a-z]*" if language is None else re.escape(language)
    commands = []
    for block in re.findall(rf"^ *```{fence}\n(.*?)^ *```", text, flags=re.M | re.S):
        if re.search(r"^ *\$ ", block, flags=re.M):
            continue
        joined = re.sub(r"\\\n\s*", " ", block)
        lines = [re.sub(r"\s+#\s.*$", "", line).strip() for line in joined.splitlines()]
        commands += [line for line in lines if line.startswith(prefixes)]
    return commands


def run_rangeret(words: list[str], command: str) -> str:
    """`rangeret WORDS...` (the words after `rangeret`, a `> FILE` at their end taking its
    standard output) in a process of its own, which must exit 0; `command` names it in a
    failure. Its standard output."""
    target = None
    if ">" in words:
        words, target = words[: words.index(">")], words[words.index(">") + 1]
    done = subprocess.run(
        [sys.executable, "-m", "rangeret.cli.main", *words],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, f"{command}\n{done.stderr[-3000:]}"
    if target is not None:
        Path(target).write_text(done.stdout)
    return done.stdout
