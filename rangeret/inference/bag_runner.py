"""Labelling a bag: every PointCloud2 message of one topic gets `label` and `confidence` fields
(and with panoptic segmentation `instance`), everything else in the bag is copied as it was.

Each message of the topic is read into the profile's point record
(`rangeret.io.pointcloud2.read_cloud`), labelled (`label_cloud`, the path every runner shares) and
written back with the new fields after its own (`append_labels`: every field and point kept in
order; header and timestamp unchanged). A message that cannot be labelled (a bad layout, a missing
field, a laser id outside the sensor's rows, more objects than the benchmark's panoptic label
holds) is written through unchanged and listed in the run record, so no message is lost; the run
then ends as failed. The new bag appears at its name only once complete
(`rangeret.io.bags.atomic_bag`), its run record at `OUT.run.json` beside it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from rangeret.exceptions import InputError
from rangeret.inference.clouds import label_cloud, problem_kind
from rangeret.inference.files_runner import field_labels
from rangeret.inference.predictor import Predictor
from rangeret.io.bags import SourceBag, atomic_bag, bag_format, check_target, open_bag
from rangeret.io.bags import run_record_path as record_path
from rangeret.io.pointcloud2 import append_labels, read_cloud
from rangeret.io.run_info import started_now, write_run_record

log = logging.getLogger(__name__)

RUNNER = "rangeret predict --bag"


@dataclass
class BagSummary:
    """What a bag run read, labelled and wrote."""

    source: Path
    target: Path
    topic: str
    source_format: str
    target_format: str
    messages: int = 0
    labelled: int = 0
    points: int = 0
    invalid_points: int = 0
    other_messages: int = 0
    #: With panoptic segmentation, the objects found, summed over the labelled messages.
    instances: int | None = None
    #: Each message written through unlabelled: its index on the topic, timestamp, kind, reason.
    failed: list[dict[str, Any]] = field(default_factory=list)
    #: The distinct ways the point record was filled ({record value: source field or `fill V`}).
    field_sources: list[dict[str, str]] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        """Whether every message of the topic was labelled."""
        return not self.failed

    def record(self, reflectance_fill: float) -> dict[str, Any]:
        """The run record's account of the bag (beside the network's description)."""
        return {
            "input_bag": str(self.source),
            "output_bag": str(self.target),
            "topic": self.topic,
            "storage_in": self.source_format,
            "storage_out": self.target_format,
            "messages": self.messages,
            "messages_labelled": self.labelled,
            "messages_failed": len(self.failed),
            "failed": self.failed,
            "other_messages": self.other_messages,
            "points": self.points,
            "invalid_points": self.invalid_points,
            **({} if self.instances is None else {"instances": self.instances}),
            "field_sources": self.field_sources,
            "reflectance_fill": reflectance_fill,
            "seconds": round(self.seconds, 3),
        }

    def text(self) -> str:
        """One line for the terminal."""
        return (
            f"{self.topic}: {self.messages} messages, {self.labelled} labelled, "
            f"{len(self.failed)} written through unlabelled; {self.other_messages} other "
            f"messages copied; {self.points} points -> {self.target}"
        )


def label_bag(
    predictor: Predictor,
    source: Path,
    topic: str,
    target: Path,
    *,
    target_format: str | None = None,
    overrides: Mapping[str, str] | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> BagSummary:
    """Write `target`, a copy of bag `source` (in `target_format`, default the source's) whose
    `topic` messages carry `label` (UINT32 raw ids) and `confidence` (FLOAT32) fields (with
    panoptic segmentation `instance`, UINT32, too), and its run record beside it; see the module
    docstring. A bad bag, topic or target is a BagError and leaves nothing at `target`."""
    started = started_now()
    start = time.perf_counter()
    fmt_in = bag_format(source)
    fmt_out = target_format or fmt_in
    check_target(target, fmt_out, overwrite=overwrite, source=source)
    with open_bag(source) as bag:
        cloud_topic = bag.cloud_topic(topic)
        summary = BagSummary(source, target, topic, fmt_in, fmt_out)
        if predictor.clustering is not None:
            summary.instances = 0
        bar = tqdm(total=cloud_topic.count, desc="label", unit="msg", disable=not progress)
        with (
            atomic_bag(target, fmt_out, overwrite=overwrite) as path,
            bag.copy_to(path, fmt_out) as out,
        ):
            for conn, timestamp, raw in bag.messages():
                if conn.topic != topic:
                    out.write(conn, timestamp, raw)
                    summary.other_messages += 1
                    continue
                out.write(
                    conn, timestamp, _labelled(predictor, bag, summary, raw, timestamp, overrides)
                )
                bar.update(1)
        bar.close()
    summary.seconds = time.perf_counter() - start
    write_run_record(
        record_path(target),
        predictor.describe(),
        runner=RUNNER,
        details=summary.record(predictor.profile.reflectance_fill),
        started=started,
    )
    return summary


def _labelled(
    predictor: Predictor,
    bag: SourceBag,
    summary: BagSummary,
    raw: bytes,
    timestamp: int,
    overrides: Mapping[str, str] | None,
) -> bytes:
    """The message's bytes with labels and confidences added, or its own bytes (the failure
    counted and logged once per kind) when it cannot be labelled."""
    index = summary.messages
    summary.messages += 1
    source = f"{bag.path}: {summary.topic} message {index} (t={timestamp})"
    profile = predictor.profile
    try:
        msg = bag.decode(raw, "sensor_msgs/msg/PointCloud2", source)
        layout, cloud = read_cloud(
            msg,
            source,
            record=profile.points,
            reflectance_fill=profile.reflectance_fill,
            overrides=overrides,
        )
        labels = label_cloud(predictor, cloud)
    except InputError as exc:
        kind = problem_kind(exc)
        if all(f["kind"] != kind for f in summary.failed):
            log.warning(
                "%s; written through unlabelled (further %s problems: debug log)", exc, kind
            )
        else:
            log.debug("%s; written through unlabelled", exc)
        summary.failed.append(
            {"index": index, "timestamp": timestamp, "kind": kind, "reason": str(exc)}
        )
        return raw
    fields, step, data = append_labels(
        layout,
        msg.data,
        field_labels(predictor, labels),
        labels.confidence,
        instances=labels.instances,
    )
    summary.labelled += 1
    if summary.instances is not None:
        summary.instances += labels.num_instances
    summary.points += cloud.num_points
    summary.invalid_points += cloud.num_invalid
    if cloud.sources not in summary.field_sources:
        summary.field_sources.append(dict(cloud.sources))
    return bag.encode_cloud(msg, fields, step, data)
