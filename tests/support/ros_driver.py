"""The driver of the node's tests, run inside the isolated namespace (see `tests.support.ros`):
`python -m tests.support.ros_driver JOB.json`.

Starts `rangeret ros2` as a child (its output in node.log), waits until it subscribes and
publishes (and, with the job's `idle_s`, that much longer, or until its log holds `idle_until`),
then publishes each cloud of the job
in turn, reliable or best effort as a driver does (`input_reliable`): a cloud expecting an answer
is sent again every few seconds until its answer (matched by header stamp) arrives, or with
`resend` false sent once; after a bad one it waits until /diagnostics counts it. Then it waits
for one more report, stops the node with the job's signal and writes result.json (with each
cloud's sends and seconds to its answer) and answers.npz.
"""

from __future__ import annotations

import array
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2, PointField

from tests.support.ros import Cloud

STARTUP_S = 180.0
ANSWER_S = 90.0
RESEND_S = 5.0


def to_message(cloud: Cloud) -> PointCloud2:
    """The rclpy message of a test cloud."""
    msg = PointCloud2()
    msg.header.frame_id = cloud.frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = cloud.stamp
    msg.height, msg.width = cloud.height, cloud.width
    msg.fields = [
        PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
        for f in cloud.fields
    ]
    msg.is_bigendian, msg.is_dense = cloud.is_bigendian, cloud.is_dense
    msg.point_step, msg.row_step = cloud.point_step, cloud.row_step
    data = array.array("B")
    data.frombytes(cloud.data)
    msg.data = data
    return msg


def from_message(msg: PointCloud2) -> Cloud:
    """A received message as a test cloud."""
    meta = {
        "fields": [[f.name, f.offset, f.datatype, f.count] for f in msg.fields],
        "height": msg.height,
        "width": msg.width,
        "point_step": msg.point_step,
        "row_step": msg.row_step,
        "is_bigendian": msg.is_bigendian,
        "is_dense": msg.is_dense,
        "frame_id": msg.header.frame_id,
        "stamp": [msg.header.stamp.sec, msg.header.stamp.nanosec],
    }
    return Cloud.from_meta(meta, bytes(msg.data))


class Driver(Node):
    """Publishes the test clouds, keeps the answers and the latest diagnostics."""

    def __init__(self, job: dict) -> None:
        super().__init__("rangeret_test_driver")
        reliable = QoSProfile(
            depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE
        )
        answers = QoSProfile(
            depth=10,
            history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.RELIABLE
            if job["output_reliable"]
            else ReliabilityPolicy.BEST_EFFORT,
        )
        self.publisher = self.create_publisher(
            PointCloud2,
            job["input_topic"],
            reliable if job.get("input_reliable", True) else qos_profile_sensor_data,
        )
        self.answers: dict[tuple[int, int], Cloud] = {}
        self.reports: list[tuple[dict[str, str], dict[str, str]]] = []
        self.answer_sub = self.create_subscription(
            PointCloud2, job["output_topic"], self._answer, answers
        )
        self.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, reliable)

    def _answer(self, msg: PointCloud2) -> None:
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        self.answers.setdefault(key, from_message(msg))

    def _diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            info = {"name": status.name, "message": status.message, "level": str(status.level[0])}
            self.reports.append((values, info))

    def bad_count(self) -> int:
        return int(self.reports[-1][0]["bad"]) if self.reports else 0


def spin_until(node: Driver, done, seconds: float, child: subprocess.Popen) -> bool:
    """Spin until `done()` holds (True), `seconds` pass or the node exits (False)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if done():
            return True
        if child.poll() is not None:
            return False
        rclpy.spin_once(node, timeout_sec=0.05)
    return done()


def log_text(folder: Path) -> str:
    """The node's log so far."""
    return (folder / "node.log").read_text(errors="replace")


def main(job_path: str) -> int:
    job = json.loads(Path(job_path).read_text())
    folder = Path(job["folder"])
    stored = np.load(folder / "clouds.npz")
    clouds = [Cloud.from_meta(m, stored[f"c{i}"].tobytes()) for i, m in enumerate(job["clouds"])]
    with open(folder / "node.log", "w") as log:
        child = subprocess.Popen(
            [sys.executable, "-m", "rangeret.cli", "ros2", *job["node_args"]],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    rclpy.init()
    node = Driver(job)
    result: dict = {"answers": {}, "sent": [], "events": []}
    try:
        ready = spin_until(
            node,
            lambda: (
                node.publisher.get_subscription_count() > 0
                and node.answer_sub.get_publisher_count() > 0
            ),
            STARTUP_S,
            child,
        )
        result["events"].append(f"ready {ready}")
        if ready and job.get("idle_s"):
            logged = job.get("idle_until")
            spin_until(
                node, lambda: bool(logged) and logged in log_text(folder), job["idle_s"], child
            )
        resend = RESEND_S if job.get("resend", True) else job.get("answer_s", ANSWER_S)
        result["sends"], result["answer_s"] = {}, {}
        bad = 0
        for i, cloud in enumerate(clouds):
            if not ready:
                break
            msg, key = to_message(cloud), tuple(cloud.stamp)
            if cloud.expect == "bad":
                bad += 1
                node.publisher.publish(msg)
                result["sent"].append(i)
                ok = spin_until(node, lambda b=bad: node.bad_count() >= b, ANSWER_S, child)
            else:
                started = time.monotonic()
                deadline = started + job.get("answer_s", ANSWER_S)
                ok = False
                while not ok and time.monotonic() < deadline and child.poll() is None:
                    node.publisher.publish(msg)
                    result["sent"].append(i)
                    ok = spin_until(node, lambda k=key: k in node.answers, resend, child)
                result["sends"][str(i)] = result["sent"].count(i)
                if ok:
                    result["answers"][str(i)] = node.answers[key].meta()
                    result["answer_s"][str(i)] = time.monotonic() - started
            result["events"].append(f"cloud {i} {'ok' if ok else 'timed out'}")
        seen = len(node.reports)
        spin_until(node, lambda: len(node.reports) > seen, 30.0, child)
        result["diagnostics"], result["status"] = node.reports[-1] if node.reports else ({}, {})
    finally:
        if child.poll() is None:
            child.send_signal(getattr(signal, job["stop_signal"]))
        try:
            result["returncode"] = child.wait(timeout=60)
        except subprocess.TimeoutExpired:
            child.kill()
            result["returncode"] = None
        node.destroy_node()
        rclpy.shutdown()
    np.savez(
        folder / "answers.npz",
        **{
            f"a{i}": np.frombuffer(node.answers[tuple(clouds[int(i)].stamp)].data, np.uint8)
            for i in result["answers"]
        },
    )
    (folder / "result.json").write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
