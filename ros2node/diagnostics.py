"""The node's report as a `diagnostic_msgs/DiagnosticArray` for `/diagnostics`.

One `DiagnosticStatus` named `<node>: labelling`, hardware id the network's device; level OK,
or WARN when the interval skipped bad messages. Its key/values are the report's figures
(`Report.values`) and the run's fixed facts (topics, profile, weights).
"""

from __future__ import annotations

from collections.abc import Mapping

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from ros2node.stats import Report


def diagnostic_array(
    report: Report, *, name: str, hardware_id: str, facts: Mapping[str, str], stamp: Time
) -> DiagnosticArray:
    """The report (and the run's `facts`) as one status of a DiagnosticArray stamped `stamp`."""
    status = DiagnosticStatus()
    status.name = f"{name}: labelling"
    status.hardware_id = hardware_id
    if report.interval_bad:
        status.level = DiagnosticStatus.WARN
        status.message = f"skipped {report.interval_bad} bad messages in the last interval"
    else:
        status.level = DiagnosticStatus.OK
        status.message = f"labelled {report.interval_labelled} messages in the last interval"
    values = {**report.values(), **facts}
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = [status]
    return array
