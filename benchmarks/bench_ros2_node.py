"""The ROS 2 node's latency (receive -> publish) and its overhead over `Predictor.predict` alone
for the real scan (123,389 points), on the CPU, for both networks at 64 x 1024.

Each network is built with random weights (`rangeret.models.build_model`) and saved as the
project's own checkpoint. One process runs the node (`ros2node.node.LabellingNode`) and a driver
node that publishes the real scan as a PointCloud2 and waits for each answer before sending the
next, so no message is dropped. The overhead is the node's own work besides the prediction:
message -> record (decode + to_record), building the answer (append_fields + the message) and
publishing it; the node measures it per message, and its parts are also timed directly here.

Run by hand: `python benchmarks/bench_ros2_node.py [--messages N]`. As root it re-runs itself in
a loopback-only network namespace (DDS stays on this host; `--no-isolate` to skip that). Prints
milliseconds; not a test.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _common import REAL_SCAN, median_time, require_real_scan

#: Set in the re-run inside the network namespace.
ISOLATED = "RANGERET_BENCH_ISOLATED"
NETWORKS = ("rangeret-cir", "rangeret-thesis")
NAMES = ("x", "y", "z", "intensity")


def isolate(argv: list[str]) -> None:
    """Re-run this script in a fresh loopback-only network namespace, when root can make one."""
    if os.environ.get(ISOLATED) or os.geteuid() != 0 or not shutil.which("unshare"):
        return
    os.environ[ISOLATED] = "1"
    shell = 'ip link set lo up && exec "$@"'
    os.execvp("unshare", ["unshare", "-n", "sh", "-c", shell, "sh", sys.executable, *argv])


def real_scan_message(points):
    """The real scan as a dense PointCloud2 of float32 x, y, z, intensity."""
    import array

    import numpy as np
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.frame_id = "velodyne"
    msg.height, msg.width = 1, len(points)
    msg.fields = [
        PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate(NAMES)
    ]
    msg.point_step, msg.row_step = 16, 16 * len(points)
    data = array.array("B")
    data.frombytes(np.ascontiguousarray(points, dtype=np.float32).tobytes())
    msg.data = data
    msg.is_dense = True
    return msg


def checkpoint(name: str, folder: Path) -> Path:
    """Random-init weights of network `name` at 64 x 1024, saved as the project's checkpoint."""
    from rangeret.dataset.profiles import load_profile
    from rangeret.models import build_model
    from rangeret.models.weights.checkpoint import save_checkpoint

    profile = load_profile("semantickitti")
    path = folder / f"{name}.pt"
    save_checkpoint(
        path,
        build_model(name, 64, 1024),
        label_config=profile.labels,
        projection=profile.projection,
        profile=profile.to_dict(),
    )
    return path


def run_network(path: Path, points, args: argparse.Namespace) -> dict[str, float]:
    """The node's figures for one checkpoint (milliseconds)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from rangeret.inference.clouds import label_cloud
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.spec import InferenceSpec
    from ros2node.clouds import FieldMapping, cloud_record, labelled_message
    from ros2node.node import LabellingNode, qos_profile
    from ros2node.options import NodeSettings

    predictor = Predictor.from_spec(InferenceSpec(checkpoint=str(path), device=args.device))
    profile = predictor.profile
    mapping = FieldMapping(profile.points, profile.reflectance_fill, {})
    msg = real_scan_message(points)
    figures = {
        "predict": 1e3 * median_time(lambda: predictor.predict(points), repeat=args.repeat),
    }
    layout, cloud = cloud_record(msg, "bench", mapping)
    labels = label_cloud(predictor, cloud)
    figures["label_cloud"] = 1e3 * median_time(
        lambda: label_cloud(predictor, cloud), repeat=args.repeat
    )
    figures["record"] = 1e3 * median_time(lambda: cloud_record(msg, "bench", mapping), repeat=50)
    figures["answer"] = 1e3 * median_time(lambda: labelled_message(msg, layout, labels), repeat=50)

    settings = NodeSettings("points", "points_labelled", "reliable", "reliable", False, 1e6)
    rclpy.init()
    try:
        node = LabellingNode(predictor, settings, mapping)
        driver = Node("bench_driver")
        qos = QoSProfile(
            depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE
        )
        publisher = driver.create_publisher(PointCloud2, "points", qos)
        answers: list[float] = []
        driver.create_subscription(
            PointCloud2, "points_labelled", lambda _m: answers.append(time.perf_counter()), qos
        )
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.add_node(driver)
        while publisher.get_subscription_count() == 0:
            executor.spin_once(timeout_sec=0.05)
        # publishing alone, on a probe topic of the output's QoS (its answers would otherwise
        # reach the driver's subscription and be taken for the node's)
        probe = node.create_publisher(PointCloud2, "publish_probe", qos_profile("reliable"))
        driver.create_subscription(PointCloud2, "publish_probe", lambda _m: None, qos)
        while probe.get_subscription_count() == 0:
            executor.spin_once(timeout_sec=0.05)
        answer = labelled_message(msg, layout, labels)
        figures["publish"] = 1e3 * median_time(lambda: probe.publish(answer), repeat=20)
        for _ in range(10):  # let the probe's messages be taken before the node's run
            executor.spin_once(timeout_sec=0.05)
        round_trips = []
        for i in range(args.messages + 1):
            if i == 1:  # the first message warms up; the node's report starts after it
                node.stats.report(node.mailbox.dropped, 0.0)
            seen = len(answers)
            sent = time.perf_counter()
            publisher.publish(msg)
            while len(answers) == seen:
                executor.spin_once(timeout_sec=0.05)
            round_trips.append(1e3 * (answers[-1] - sent))
        report = node.stats.report(node.mailbox.dropped, 0.0)
        node.close()
        executor.shutdown()
        node.destroy_node()
        driver.destroy_node()
    finally:
        rclpy.try_shutdown()
    figures.update(
        latency_p50=report.latency_p50_ms,
        latency_p95=report.latency_p95_ms,
        overhead_p50=report.overhead_p50_ms,
        overhead_p95=report.overhead_p95_ms,
        round_trip_p50=statistics.median(round_trips[1:]),
        dropped=float(report.dropped),
        labelled=float(report.interval_labelled),
    )
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--messages", type=int, default=20, help="scans sent to the node")
    parser.add_argument("--repeat", type=int, default=5, help="samples of predict alone")
    parser.add_argument("--domain-id", type=int, default=77, help="ROS_DOMAIN_ID of the run")
    parser.add_argument("--no-isolate", action="store_true", help="no network namespace")
    args = parser.parse_args()
    require_real_scan()
    if not args.no_isolate:
        isolate([str(Path(__file__).resolve()), *sys.argv[1:]])
    os.environ.update(
        ROS_DOMAIN_ID=str(args.domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOCALHOST_ONLY="1",
        RMW_IMPLEMENTATION=os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp"),
    )
    import torch

    from rangeret.io.scans import KITTI_RECORD, read_scan

    points = read_scan(REAL_SCAN, KITTI_RECORD)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}, "
        f"{len(points):,} points at 64 x 1024, {args.messages} messages"
        f"{', loopback-only namespace' if os.environ.get(ISOLATED) else ''}"
    )
    header = (
        f"  {'network':<16} {'predict':>8} {'label':>8} {'latency p50':>12} {'p95':>8} "
        f"{'overhead p50':>13} {'p95':>6} {'record':>7} {'answer':>7} {'publish':>8} "
        f"{'round trip':>11}"
    )
    print("milliseconds (predict: Predictor.predict alone; label: label_cloud, with confidence):")
    print(header)
    with tempfile.TemporaryDirectory() as tmp:
        for name in NETWORKS:
            f = run_network(checkpoint(name, Path(tmp)), points, args)
            print(
                f"  {name:<16} {f['predict']:8.1f} {f['label_cloud']:8.1f} "
                f"{f['latency_p50']:12.1f} {f['latency_p95']:8.1f} {f['overhead_p50']:13.2f} "
                f"{f['overhead_p95']:6.2f} {f['record']:7.2f} {f['answer']:7.2f} "
                f"{f['publish']:8.2f} {f['round_trip_p50']:11.1f}"
                f"   (labelled {f['labelled']:.0f}, dropped {f['dropped']:.0f})"
            )


if __name__ == "__main__":
    main()
