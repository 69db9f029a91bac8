"""The official nuScenes devkit (`nuscenes-devkit==1.2.0`) in a cached venv of its own, for tests.

The devkit pins numpy<2, so it never goes into the project's venv: `devkit_python()` builds a
separate venv once (minutes; later calls only check its stamp) under `RANGERET_DEVKIT_VENV`, or
`~/.cache/rangeret/nuscenes-devkit-1.2.0`, and `run_devkit()` runs `devkit_check.py` with it.
Two processes building at once wait on an `fcntl.flock` of `<venv>.lock`; the venv is built in
place (venvs are not relocatable) and counts as built only once its stamp file is written, after
the install and an import check, so a half-built one is removed and rebuilt.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger(__name__)

DEVKIT_VERSION = "1.2.0"
REQUIREMENT = f"nuscenes-devkit=={DEVKIT_VERSION}"
CHECK_IMPORT = "import nuscenes.eval.lidarseg.evaluate, nuscenes.eval.lidarseg.validate_submission"
SCRIPT = Path(__file__).with_name("devkit_check.py")
STAMP = ".rangeret-devkit-stamp"
INSTALL_TIMEOUT_S = 1800.0
TAIL_CHARS = 4000

# Variables that would let the caller's environment leak into the devkit's interpreter.
_LEAKY_ENV = ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "VIRTUAL_ENV", "PIP_REQUIRE_VIRTUALENV")


def venv_dir() -> Path:
    """Where the devkit venv is cached: `$RANGERET_DEVKIT_VENV` or under `~/.cache/rangeret`."""
    default = Path.home() / ".cache" / "rangeret" / f"nuscenes-devkit-{DEVKIT_VERSION}"
    return Path(os.environ.get("RANGERET_DEVKIT_VENV", default)).expanduser().absolute()


def base_python() -> Path:
    """The interpreter the venv is built from: the caller's base python, not its venv's."""
    if sys.prefix == sys.base_prefix:
        return Path(sys.executable)
    base = getattr(sys, "_base_executable", None)
    if base and Path(base).exists() and Path(base).resolve() != Path(sys.executable).resolve():
        return Path(base)
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    for name in (version, "python3", "python"):
        candidate = Path(sys.base_prefix) / "bin" / name
        if candidate.exists():
            return candidate
    raise RuntimeError(f"no base python found under {sys.base_prefix}/bin for the devkit venv")


def clean_env() -> dict[str, str]:
    """The environment for the devkit's processes: no caller venv or PYTHONPATH, headless plots."""
    env = {k: v for k, v in os.environ.items() if k not in _LEAKY_ENV}
    env["MPLBACKEND"] = "Agg"
    env["PYTHONNOUSERSITE"] = "1"
    return env


def _tail(text: str, chars: int = TAIL_CHARS) -> str:
    """The last `chars` characters of `text`, marked when cut."""
    return text if len(text) <= chars else "...\n" + text[-chars:]


def _is_built(root: Path) -> bool:
    """Whether the venv at `root` finished building (its stamp names this requirement)."""
    stamp = root / STAMP
    python = root / "bin" / "python"
    try:
        return python.exists() and stamp.read_text().splitlines()[0] == REQUIREMENT
    except (OSError, IndexError):
        return False


def _step(what: str, cmd: list[str], timeout: float) -> str:
    """Run one build step, logging it; its output, or RuntimeError with the output's tail."""
    log.info("devkit venv: %s", what)
    start = time.monotonic()
    try:
        proc = subprocess.run(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=timeout,
            env=clean_env(),
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        out = (
            exc.stdout
            if isinstance(exc.stdout, str)
            else (exc.stdout or b"").decode(errors="replace")
        )
        raise RuntimeError(
            f"devkit venv: {what} timed out after {timeout:.0f} s:\n{_tail(out)}"
        ) from exc
    log.debug("devkit venv: %s output:\n%s", what, proc.stdout)
    if proc.returncode != 0:
        raise RuntimeError(
            f"devkit venv: {what} failed (exit {proc.returncode}): {' '.join(cmd)}\n"
            f"{_tail(proc.stdout)}"
        )
    log.info("devkit venv: %s done in %.1f s", what, time.monotonic() - start)
    return proc.stdout


def _build(root: Path) -> None:
    """Build the venv at `root` from scratch and stamp it."""
    if root.exists():
        log.warning("devkit venv: removing the unfinished venv at %s", root)
        shutil.rmtree(root)
    start = time.monotonic()
    python = root / "bin" / "python"
    _step(f"create {root} with {base_python()}", [str(base_python()), "-m", "venv", str(root)], 300)
    pip = [str(python), "-m", "pip", "--disable-pip-version-check", "--no-input"]
    log.info("devkit venv: installing %s takes a minute or more", REQUIREMENT)
    _step(f"pip install {REQUIREMENT}", [*pip, "install", REQUIREMENT], INSTALL_TIMEOUT_S)
    _step("check import", [str(python), "-c", CHECK_IMPORT], 300)
    freeze = _step("pip freeze", [*pip, "freeze"], 300)
    tmp = root / (STAMP + ".tmp")
    tmp.write_text(f"{REQUIREMENT}\n{freeze}")
    os.replace(tmp, root / STAMP)
    log.info("devkit venv: built %s in %.1f s", root, time.monotonic() - start)


def devkit_python() -> Path:
    """The python of a venv with `nuscenes-devkit==1.2.0`, building the cached venv if needed."""
    root = venv_dir()
    python = root / "bin" / "python"
    if _is_built(root):
        return python
    root.parent.mkdir(parents=True, exist_ok=True)
    with open(root.with_name(root.name + ".lock"), "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("devkit venv: waiting for another process building %s", root)
            fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not _is_built(root):
                _build(root)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return python


def run_devkit(*args: str | os.PathLike[str], timeout: float = 600) -> dict:
    """Run `devkit_check.py ARGS` with the devkit's python; its JSON, or AssertionError on failure."""
    argv = [os.fspath(a) for a in args]
    cmd = [str(devkit_python()), "-I", str(SCRIPT), *argv]
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=timeout, env=clean_env(), check=False
    )
    if proc.returncode != 0:
        raise AssertionError(
            f"devkit_check.py {' '.join(argv)} exited with {proc.returncode}:\n{_tail(proc.stderr)}"
        )
    try:
        result = json.loads(proc.stdout)
    except json.JSONDecodeError as exc:
        raise AssertionError(
            f"devkit_check.py {' '.join(argv)} printed no JSON ({exc}):\n{_tail(proc.stdout)}\n"
            f"stderr:\n{_tail(proc.stderr)}"
        ) from exc
    if not isinstance(result, dict):
        raise AssertionError(f"devkit_check.py {' '.join(argv)} printed {type(result).__name__}")
    return result
