"""Running `rangeret ros2` in isolation and talking to it, for the ROS 2 node's tests.

Every run has its own `ROS_DOMAIN_ID`, discovery limited to the host
(`ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`, and `ROS_LOCALHOST_ONLY=1` for older RMWs), and runs
inside a network namespace holding only a loopback interface (`unshare -n`, or `unshare -rn`
where not root), so no DDS packet can leave the machine. As root the namespace is required (a
run fails without one); a user who cannot make one runs with the host-only discovery alone. The driver (`tests.support.ros_driver`)
runs in that namespace: it starts the node as its child, publishes the test's messages, collects
the answers and `/diagnostics`, stops the node with a signal and writes everything to files.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from rangeret.io.pointcloud2 import DATATYPES, CloudField
from tests.support.paths import REPO

#: Environment variables of ROS 2 and its DDS implementations, which no test run inherits.
_MIDDLEWARE_PREFIXES = ("ROS_", "RMW_", "FASTDDS_", "FASTRTPS_", "CYCLONEDDS_")

#: The shell step that brings the namespace's loopback up before running the command.
_LOOPBACK = 'ip link set lo up && exec "$@"'


@functools.cache
def namespace_prefix() -> tuple[str, ...]:
    """The command prefix that runs a command in a fresh loopback-only network namespace; empty
    for a user who cannot make one (host-only discovery still applies). As root, a machine that
    cannot make one fails the test: no DDS packet may leave it."""
    root = os.geteuid() == 0
    tools = shutil.which("unshare") is not None and shutil.which("ip") is not None
    for flags in (("-n",), ("-rn",)) if root else (("-rn",),):
        if not tools:
            break
        prefix = ("unshare", *flags, "sh", "-c", _LOOPBACK, "sh")
        probe = subprocess.run([*prefix, "true"], capture_output=True, timeout=30, check=False)
        if probe.returncode == 0:
            return prefix
    if root:
        pytest.fail("as root, the ROS 2 tests run in a loopback-only namespace: unshare -n failed")
    return ()


def ros_environment(domain_id: int) -> dict[str, str]:
    """The environment of an isolated ROS 2 run on `domain_id`, this checkout importable."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(_MIDDLEWARE_PREFIXES)}
    env.update(
        ROS_DOMAIN_ID=str(domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOCALHOST_ONLY="1",
        RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
        PYTHONPATH=str(REPO),
        HF_HUB_OFFLINE="1",
        PYTHONUNBUFFERED="1",
    )
    return env


def domain_id_for(offset: int) -> int:
    """A domain id for one test module (`offset` distinct per module), varied by process."""
    return 10 + (os.getpid() * 7 + offset) % 90


@dataclass
class Cloud:
    """A PointCloud2 as the driver publishes it (and as `rangeret.io.pointcloud2` reads it)."""

    fields: list[CloudField]
    height: int
    width: int
    point_step: int
    row_step: int
    data: bytes
    is_bigendian: bool = False
    is_dense: bool = True
    frame_id: str = "lidar"
    stamp: tuple[int, int] = (0, 0)
    #: What the test expects: "answer" (a labelled cloud comes back) or "bad" (skipped).
    expect: str = "answer"

    def meta(self) -> dict:
        """Everything but the data, as JSON."""
        return {
            "fields": [[f.name, f.offset, f.datatype, f.count] for f in self.fields],
            "height": self.height,
            "width": self.width,
            "point_step": self.point_step,
            "row_step": self.row_step,
            "is_bigendian": self.is_bigendian,
            "is_dense": self.is_dense,
            "frame_id": self.frame_id,
            "stamp": list(self.stamp),
            "expect": self.expect,
        }

    @classmethod
    def from_meta(cls, meta: dict, data: bytes) -> Cloud:
        """The cloud of `meta()` and its data."""
        fields = [CloudField(n, o, d, c) for n, o, d, c in meta["fields"]]
        keys = ("height", "width", "point_step", "row_step", "is_bigendian", "is_dense")
        return cls(
            fields,
            data=data,
            frame_id=meta["frame_id"],
            stamp=tuple(meta["stamp"]),
            expect=meta.get("expect", "answer"),
            **{k: meta[k] for k in keys},
        )


def make_cloud(
    columns: dict[str, tuple[int, np.ndarray]],
    *,
    height: int = 1,
    point_step: int | None = None,
    gaps: int = 0,
    row_padding: int = 0,
    bigendian: bool = False,
    **kwargs,
) -> Cloud:
    """A cloud of `columns` ({name: (datatype, values)}, in order), `gaps` unused bytes before
    each field after the first, the point step given or dense, `row_padding` bytes after each of
    `height` rows."""
    order = ">" if bigendian else "<"
    fields, offset = [], 0
    for i, (name, (datatype, _)) in enumerate(columns.items()):
        offset += gaps if i else 0
        fields.append(CloudField(name, offset, datatype))
        offset += np.dtype(DATATYPES[datatype]).itemsize
    step = point_step or offset
    dtype = np.dtype(
        {
            "names": list(columns),
            "formats": [order + DATATYPES[d] for d, _ in columns.values()],
            "offsets": [f.offset for f in fields],
            "itemsize": step,
        }
    )
    n = len(next(iter(columns.values()))[1])
    records = np.zeros(n, dtype=dtype)
    for name, (_, values) in columns.items():
        records[name] = values
    width = n // height
    rows = records.view(np.uint8).reshape(height, width * step)
    data = np.concatenate([rows, np.zeros((height, row_padding), np.uint8)], axis=1).tobytes()
    return Cloud(fields, height, width, step, width * step + row_padding, data, bigendian, **kwargs)


@dataclass
class Drive:
    """What a driver run saw: the answers (by message index), the last diagnostics' key/values
    and status, the node's exit code and its log."""

    answers: dict[int, Cloud]
    diagnostics: dict[str, str]
    status: dict[str, str]
    returncode: int | None
    log: str
    driver_log: str = ""
    extra: dict = field(default_factory=dict)


def drive_node(
    folder: Path,
    node_args: list[str],
    clouds: list[Cloud],
    *,
    domain_id: int,
    stop_signal: str = "SIGTERM",
    input_topic: str = "points",
    output_topic: str = "points_labelled",
    output_reliable: bool = True,
    input_reliable: bool = True,
    resend: bool = True,
    answer_s: float | None = None,
    idle_s: float = 0.0,
    idle_until: str | None = None,
    env: dict[str, str] | None = None,
    timeout: float = 240.0,
) -> Drive:
    """Start `rangeret ros2 NODE_ARGS` in an isolated namespace (`env` added to its
    environment), wait `idle_s` once it is matched (or until its log holds `idle_until`), publish `clouds` one after the other, reliable
    or best effort (waiting for each answer, sent again every few seconds unless `resend` is
    false, or for /diagnostics to count each bad one), stop it with `stop_signal` and return
    what came back."""
    prefix = namespace_prefix()
    folder.mkdir(parents=True, exist_ok=True)
    job = {
        "node_args": node_args,
        "input_topic": input_topic,
        "output_topic": output_topic,
        "output_reliable": output_reliable,
        "input_reliable": input_reliable,
        "resend": resend,
        "idle_s": idle_s,
        "idle_until": idle_until,
        "stop_signal": stop_signal,
        "clouds": [c.meta() for c in clouds],
        "folder": str(folder),
    }
    np.savez(
        folder / "clouds.npz",
        **{f"c{i}": np.frombuffer(c.data, np.uint8) for i, c in enumerate(clouds)},
    )
    if answer_s is not None:
        job["answer_s"] = answer_s
    (folder / "job.json").write_text(json.dumps(job))
    run = subprocess.run(
        [*prefix, sys.executable, "-m", "tests.support.ros_driver", str(folder / "job.json")],
        cwd=REPO,
        env={**ros_environment(domain_id), **(env or {})},
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    node_log = (folder / "node.log").read_text() if (folder / "node.log").exists() else ""
    result_path = folder / "result.json"
    if run.returncode != 0 or not result_path.exists():
        pytest.fail(
            f"the driver failed ({run.returncode}):\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}"
            f"\nnode log:\n{node_log[-4000:]}"
        )
    result = json.loads(result_path.read_text())
    answers = np.load(folder / "answers.npz")
    return Drive(
        answers={
            int(i): Cloud.from_meta(meta, answers[f"a{i}"].tobytes())
            for i, meta in result["answers"].items()
        },
        diagnostics=result["diagnostics"],
        status=result["status"],
        returncode=result["returncode"],
        log=node_log,
        driver_log=run.stdout + run.stderr,
        extra=result,
    )
