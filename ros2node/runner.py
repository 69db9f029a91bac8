"""`rangeret ros2`'s body: load the network, start ROS 2, spin until SIGINT or SIGTERM, stop.

Before rclpy starts, the node gives its own process a Fast DDS transport profile unless the user
has configured the middleware (`ros2node.transport`); the file is removed once ROS 2 is shut
down.

The node installs its own SIGINT and SIGTERM handlers (rclpy's are turned off), which only set a
flag: the executor spins in short steps and, once the flag is set, the labelling thread finishes
its message, the node is destroyed and rclpy shut down, and the command exits 0.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from rangeret.inference.spec import InferenceSpec
from rangeret.io.point_fields import parse_field_overrides
from ros2node.clouds import FieldMapping
from ros2node.options import NodeSettings, settings_from_args
from ros2node.transport import Transport, apply_transport_profile

if TYPE_CHECKING:
    from rangeret.inference.predictor import Predictor
    from ros2node.node import LabellingNode

log = logging.getLogger("rangeret.ros2")

#: How long one executor step waits for work before it looks at the stop flag (seconds).
SPIN_STEP = 0.1


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event that SIGINT or SIGTERM sets while the block runs (the old handlers restored)."""
    stop = threading.Event()
    signals = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in signals}
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def run_node(args: argparse.Namespace) -> int:
    """Run the labelling node until SIGINT or SIGTERM; 0 when stopped by one."""
    settings = settings_from_args(args)
    with stop_on_signals() as stop:
        from rangeret.inference.predictor import Predictor

        predictor = Predictor.from_spec(InferenceSpec.from_args(args))
        profile = predictor.profile
        mapping = FieldMapping(
            record=profile.points,
            reflectance_fill=profile.reflectance_fill,
            overrides=parse_field_overrides(settings.fields, record=profile.points),
        )
        if stop.is_set():
            return 0
        transport = apply_transport_profile()
        try:
            node = _spin(predictor, settings, mapping, transport, args.ros_args, stop)
        finally:
            transport.remove()
    if node.failure is not None:
        raise node.failure
    log.info("stopped: the node is destroyed and ROS 2 shut down")
    return 0


def _spin(
    predictor: Predictor,
    settings: NodeSettings,
    mapping: FieldMapping,
    transport: Transport,
    ros_args: list[str],
    stop: threading.Event,
) -> LabellingNode:
    """Start rclpy and the node, spin until `stop` is set or the node fails, then destroy the
    node and shut rclpy down; the node, for its failure."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from ros2node.node import LabellingNode

    rclpy.init(
        args=["rangeret", "--ros-args", *ros_args],
        signal_handler_options=SignalHandlerOptions.NO,
    )
    try:
        node = LabellingNode(predictor, settings, mapping, transport)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        node.announce()
        try:
            while not stop.is_set() and node.failure is None:
                executor.spin_once(timeout_sec=SPIN_STEP)
        finally:
            node.close()
            executor.remove_node(node)
            executor.shutdown()
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return node
