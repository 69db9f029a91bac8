"""The one-slot mailbox counts what it drops; the stats give totals and interval percentiles."""

from __future__ import annotations

import threading

import pytest

from ros2node.mailbox import Mailbox, Received
from ros2node.stats import NodeStats


def test_a_message_not_taken_yet_is_replaced_and_counted():
    box = Mailbox()
    assert box.put(Received("a", 1.0)) is False
    assert box.put(Received("b", 2.0)) is True
    assert box.put(Received("c", 3.0)) is True
    assert box.dropped == 2
    assert box.take() == Received("c", 3.0)
    assert box.put(Received("d", 4.0)) is False  # the slot was empty again
    assert box.take().message == "d" and box.dropped == 2


def test_take_waits_for_a_message_and_returns_none_once_closed():
    box = Mailbox()
    taken = []
    worker = threading.Thread(target=lambda: taken.append(box.take()))
    worker.start()
    box.put(Received("a", 0.0))
    worker.join(timeout=10)
    assert not worker.is_alive() and taken[0].message == "a"
    box.put(Received("b", 0.0))
    box.close()
    assert box.take() is None  # closed: what is left is not handed out


def test_close_wakes_a_waiting_taker():
    box = Mailbox()
    result = []
    worker = threading.Thread(target=lambda: result.append(box.take()))
    worker.start()
    box.close()
    worker.join(timeout=10)
    assert result == [None]


def test_the_report_has_totals_and_the_interval_percentiles():
    stats = NodeStats()
    for ms in range(1, 101):
        stats.labelled(latency_s=ms / 1e3, overhead_s=0.002)
    assert stats.bad("size") is True
    assert stats.bad("size") is False
    assert stats.bad("fields") is True
    first = stats.report(dropped=3, interval_s=5.0)
    assert (first.labelled, first.dropped, first.bad) == (100, 3, 3)
    assert first.bad_kinds == {"size": 2, "fields": 1}
    assert (first.interval_labelled, first.interval_bad) == (100, 3)
    assert first.latency_p50_ms == pytest.approx(50.5)
    assert first.latency_p95_ms == pytest.approx(95.05)
    assert first.overhead_p50_ms == pytest.approx(2.0)
    values = first.values()
    assert values["bad_size"] == "2" and values["bad_fields"] == "1"
    assert values["latency_p50_ms"] == "50.500" and values["dropped"] == "3"
    assert "latency p50 50.5 ms, p95 95.0 ms" in first.line()

    second = stats.report(dropped=3, interval_s=5.0)  # a new interval: no timings yet
    assert (second.labelled, second.bad, second.interval_labelled, second.interval_bad) == (
        100,
        3,
        0,
        0,
    )
    assert second.latency_p50_ms is None and second.values()["latency_p95_ms"] == "n/a"
    assert "latency" not in second.line()
