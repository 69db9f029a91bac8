"""The labelling node: subscription -> one-slot mailbox -> labelling thread -> publisher.

The subscription callback (on the executor's thread) only leaves each message in the mailbox;
a thread of its own labels the newest one with `rangeret.inference.clouds.label_cloud` (with
panoptic segmentation, each point's object in an `instance` field too) and publishes the
answer, so the executor keeps taking messages (and counting the ones it drops) while the
network runs. A timer publishes the report on `/diagnostics` and logs it; another one
warns once when a matched publisher has sent nothing that arrived for `SILENCE_S` seconds.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from functools import cached_property

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

from rangeret.exceptions import InputError
from rangeret.inference.clouds import label_cloud, problem_kind
from rangeret.inference.files_runner import field_labels
from rangeret.inference.predictor import Predictor
from ros2node.clouds import FieldMapping, cloud_record, labelled_message, palette_of
from ros2node.diagnostics import diagnostic_array
from ros2node.mailbox import Mailbox, Received
from ros2node.options import INPUT_QOS_NAMES, OUTPUT_QOS_NAMES, NodeSettings
from ros2node.stats import NodeStats
from ros2node.transport import Transport, silence_advice

#: The name the node has unless `--ros-args -r __node:=NAME` renames it.
NODE_NAME = "rangeret"
#: How long a publisher may be matched with nothing received before the node warns (seconds).
SILENCE_S = 10.0
#: How often the node looks for that silence (seconds).
SILENCE_CHECK_S = 1.0


def qos_profile(choice: str) -> QoSProfile:
    """The publisher's QoS of an `--output-qos` choice (see `OUTPUT_QOS_NAMES`)."""
    if choice == "sensor":
        return qos_profile_sensor_data
    return QoSProfile(
        depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE
    )


def input_qos_profile(choice: str) -> QoSProfile:
    """The subscription's QoS of an `--input-qos` choice: a reliable one keeps 5 like sensor
    data, so the mailbox rather than DDS sees (and counts) what is dropped."""
    if choice == "sensor":
        return qos_profile_sensor_data
    return QoSProfile(
        depth=5, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE
    )


def skip_kind(exc: Exception) -> str:
    """The kind a skipped message is counted under: its input's problem (`problem_kind`), or
    `network` where the network itself failed on it (out of device memory, say)."""
    return problem_kind(exc) if isinstance(exc, InputError) else "network"


def panoptic_fact(predictor: Predictor) -> str:
    """How the log and the diagnostics name the run's panoptic segmentation: `off`, or `on` with
    its clustering settings."""
    clustering = predictor.clustering
    if clustering is None:
        return "off"
    return f"on (cluster angle {clustering.angle:g} deg, min {clustering.min_points} points)"


class LabellingNode(Node):
    """Labels every PointCloud2 of the input topic (the newest one when busy) and publishes it."""

    def __init__(
        self,
        predictor: Predictor,
        settings: NodeSettings,
        mapping: FieldMapping,
        transport: Transport | None = None,
    ):
        super().__init__(NODE_NAME)
        self.predictor = predictor
        self.transport = transport or Transport(None, "not configured by the node")
        self.settings = settings
        self.mapping = mapping
        self.palette = palette_of(predictor.profile) if settings.rgb else None
        self.mailbox = Mailbox()
        self.stats = NodeStats()
        #: An unexpected error of the labelling thread (a bug), which stops the node.
        self.failure: BaseException | None = None
        self.publisher = self.create_publisher(
            PointCloud2, settings.output_topic, qos_profile(settings.output_qos)
        )
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.subscription = self.create_subscription(
            PointCloud2,
            settings.input_topic,
            self._receive,
            input_qos_profile(settings.input_qos),
        )
        self._last_report = time.perf_counter()
        self.timer = self.create_timer(settings.report_every, self.report)
        self._received_any = False
        self._matched_since: float | None = None
        self.silence_timer = self.create_timer(SILENCE_CHECK_S, self.check_silence)
        self._worker = threading.Thread(target=self._work, name="rangeret-labelling", daemon=True)
        self._worker.start()

    @cached_property
    def facts(self) -> dict[str, str]:
        """The run's fixed facts, for the log and the diagnostics (made once)."""
        info = self.predictor.describe()
        projection = self.predictor.projection_config
        return {
            "input_topic": self.subscription.topic_name,
            "input_qos": INPUT_QOS_NAMES[self.settings.input_qos],
            "output_topic": self.publisher.topic_name,
            "output_qos": OUTPUT_QOS_NAMES[self.settings.output_qos],
            "transport": self.transport.description,
            "model": str(info["model"]),
            "checkpoint": str(info["checkpoint"]),
            "checkpoint_sha256": (info["checkpoint_sha256"] or "")[:12],
            "profile": self.predictor.profile.name,
            "resolution": f"{projection.height}x{projection.width}",
            "device": str(self.predictor.device),
            "precision": str(self.predictor.precision),
            "knn": "off" if self.predictor.knn is None else "on",
            "panoptic": panoptic_fact(self.predictor),
            "fields": ", ".join(f"{k}={v}" for k, v in self.mapping.overrides.items())
            or "by name or alias",
        }

    def announce(self) -> None:
        """The startup log line: weights, profile, device, topics and QoS."""
        f = self.facts
        self.get_logger().info(
            f"labelling {f['input_topic']} ({f['input_qos']}) into {f['output_topic']} "
            f"({f['output_qos']}{', with rgb' if self.settings.rgb else ''}) with {f['model']} "
            f"from {f['checkpoint']} (sha256 {f['checkpoint_sha256']}), {f['profile']} profile, "
            f"{f['resolution']} on {f['device']} ({f['precision']}, kNN {f['knn']}, panoptic "
            f"{f['panoptic']}); "
            f"reporting on /diagnostics every {self.settings.report_every:g} s; "
            f"DDS transport: {f['transport']}"
        )
        if (warning := self.transport.startup_warning()) is not None:
            self.get_logger().warning(warning)

    def _receive(self, msg: PointCloud2) -> None:
        self._received_any = True
        self.mailbox.put(Received(msg, time.perf_counter()))

    def check_silence(self) -> None:
        """Warn once, naming what to change, when a publisher has been matched for `SILENCE_S`
        seconds and nothing has arrived; stop looking once a message arrives."""
        if self._received_any:
            self.silence_timer.cancel()
            return
        now = time.perf_counter()
        publishers = self.subscription.get_publisher_count()
        if publishers == 0:
            self._matched_since = None
            return
        if self._matched_since is None:
            self._matched_since = now
        if now - self._matched_since < SILENCE_S:
            return
        self.silence_timer.cancel()
        topic = self.subscription.topic_name
        self.get_logger().warning(
            silence_advice(
                topic, publishers, self._publishers_reliable(topic), self.transport, SILENCE_S
            )
        )

    def _publishers_reliable(self, topic: str) -> bool | None:
        """Whether any publisher of `topic` is reliable; None when ROS 2 cannot tell."""
        try:
            infos = self.get_publishers_info_by_topic(topic)
        except Exception:  # the graph query is advice only; never stop the node for it
            return None
        if not infos:
            return None
        return any(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)

    def _work(self) -> None:
        while (item := self.mailbox.take()) is not None:
            try:
                self.label_one(item)
            except BaseException as exc:  # a bug: stop the node, which reports it
                self.failure = exc
                return

    def label_one(self, item: Received) -> None:
        """Label one message and publish the answer; a bad one is counted and skipped."""
        source = self.subscription.topic_name
        started = time.perf_counter()
        try:
            layout, cloud = cloud_record(item.message, source, self.mapping)
            decoded = time.perf_counter()
            labels = label_cloud(self.predictor, cloud)
        except (InputError, RuntimeError) as exc:
            self._skip(exc)
            return
        labelled = time.perf_counter()
        fields = dataclasses.replace(labels, labels=field_labels(self.predictor, labels))
        self.publisher.publish(labelled_message(item.message, layout, fields, self.palette))
        published = time.perf_counter()
        self.stats.labelled(
            latency_s=published - item.received,
            overhead_s=(decoded - started) + (published - labelled),
        )

    def _skip(self, exc: Exception) -> None:
        kind = skip_kind(exc)
        reason = str(exc) if isinstance(exc, InputError) else f"the network failed: {exc}"
        if self.stats.bad(kind):
            self.get_logger().warning(
                f"skipped a message: {reason} (further "
                f"{kind!r} problems are counted on /diagnostics, not logged)"
            )

    def report(self) -> None:
        """Publish the interval's report on /diagnostics and log it."""
        now = time.perf_counter()
        report = self.stats.report(self.mailbox.dropped, now - self._last_report)
        self._last_report = now
        self.diagnostics.publish(
            diagnostic_array(
                report,
                name=self.get_name(),
                hardware_id=str(self.predictor.device),
                facts=self.facts,
                stamp=self.get_clock().now().to_msg(),
            )
        )
        self.get_logger().info(report.line())

    def close(self) -> None:
        """Stop the labelling thread (after the message it is on) before the node goes."""
        self.mailbox.close()
        self._worker.join()
