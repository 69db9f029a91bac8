"""What this machine's CPU offers a network's forward pass: its model, the instruction set flags
that make bf16 and int8 matrix products fast, and the threads torch uses.

`--precision auto` picks bf16 on the CPU only where the CPU multiplies bf16 matrices in hardware
(AMX's `amx_bf16` tiles, or AVX-512's `avx512_bf16` dot products); elsewhere bf16 is emulated and
slower than fp32. The flags come from `/proc/cpuinfo` on Linux; torch's own view of the CPU
(`torch.backends.cpu.get_cpu_capability()`, e.g. "AVX512" or "AVX2") is kept beside them as a
cross-check, since it is all there is on other systems. Read once per process.
"""

from __future__ import annotations

import functools
import os
import platform
from dataclasses import dataclass, field
from pathlib import Path

#: The flags the speed card and the precision rule look at, in the order they are shown.
FLAGS = ("amx_bf16", "amx_tile", "avx512_bf16", "avx512_vnni", "avx_vnni", "avx2")
#: What each flag is, as people name it.
FLAG_NAMES = {
    "amx_bf16": "AMX bf16",
    "amx_tile": "AMX tiles",
    "avx512_bf16": "AVX-512 bf16",
    "avx512_vnni": "AVX-512 VNNI",
    "avx_vnni": "AVX-VNNI",
    "avx2": "AVX2",
}
#: The flags that give native bf16 matrix products, best first.
BF16_FLAGS = ("amx_bf16", "avx512_bf16")

CPUINFO = Path("/proc/cpuinfo")


@dataclass(frozen=True)
class CpuFeatures:
    """A CPU as the forward pass sees it: `model` name, the `flags` of `FLAGS` it has, the
    logical CPUs this process may use (`cpus`), torch's `threads` and its `capability`."""

    model: str
    flags: frozenset[str] = field(default_factory=frozenset)
    cpus: int = 1
    threads: int = 1
    capability: str | None = None

    @property
    def bf16_flag(self) -> str | None:
        """The flag that makes bf16 matrix products native here (AMX first), or None."""
        return next((f for f in BF16_FLAGS if f in self.flags), None)

    def has(self, flag: str) -> bool:
        """Whether the CPU has `flag` (a name of `FLAGS`)."""
        return flag in self.flags

    def flags_text(self) -> str:
        """The flags of `FLAGS` as `AMX bf16 yes, AVX-512 bf16 no, ...`, for people."""
        return ", ".join(f"{FLAG_NAMES[f]} {'yes' if f in self.flags else 'no'}" for f in FLAGS)

    def to_dict(self) -> dict[str, object]:
        """Plain data for JSON: model, every flag of `FLAGS` as a bool, CPUs, threads and
        torch's capability."""
        return {
            "model": self.model,
            "flags": {f: f in self.flags for f in FLAGS},
            "cpus": self.cpus,
            "torch_threads": self.threads,
            "torch_capability": self.capability,
        }


def parse_cpuinfo(text: str) -> tuple[str | None, frozenset[str]]:
    """The model name and the flags of `FLAGS` in a `/proc/cpuinfo` text (its first processor's
    `model name` and `flags` lines; an ARM `Features` line counts as flags too)."""
    model: str | None = None
    flags: frozenset[str] | None = None
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            continue
        key = key.strip().lower()
        if key == "model name" and model is None:
            model = value.strip() or None
        elif key in ("flags", "features") and flags is None:
            flags = frozenset(value.split()) & frozenset(FLAGS)
        if model is not None and flags is not None:
            break
    return model, flags or frozenset()


def usable_cpus() -> int:
    """The logical CPUs this process may run on (its affinity where the system tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def torch_capability() -> str | None:
    """Torch's view of the CPU's vector instructions ("AVX512", "AVX2", "DEFAULT", ...), or None
    where this torch cannot tell."""
    import torch

    try:
        return str(torch.backends.cpu.get_cpu_capability())
    except (AttributeError, RuntimeError):
        return None


@functools.lru_cache(maxsize=1)
def _cpuinfo() -> tuple[str | None, frozenset[str]]:
    """This machine's `/proc/cpuinfo`, parsed once (no model and no flags where there is none)."""
    try:
        return parse_cpuinfo(CPUINFO.read_text(errors="replace"))
    except OSError:
        return None, frozenset()


def cpu_features() -> CpuFeatures:
    """This machine's CPU: `/proc/cpuinfo` (read once), the usable CPUs, and torch's threads and
    capability now."""
    import torch

    model, flags = _cpuinfo()
    return CpuFeatures(
        model=model or platform.processor() or platform.machine() or "unknown CPU",
        flags=flags,
        cpus=usable_cpus(),
        threads=torch.get_num_threads(),
        capability=torch_capability(),
    )
