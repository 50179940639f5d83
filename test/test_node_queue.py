"""The node's queue from the subscription callbacks to the ingest thread: every message the
callback took reaches the ingest thread once and in order while both run, and a flood past
``max_pending`` is dropped and counted."""

from __future__ import annotations

import threading

from hammer_ros.ros.node_core import _drained, _Input, _queueing_callback


def test_every_queued_message_is_drained_once_in_order_while_the_callback_runs():
    source = _Input("excitation")
    source.pending_limit = 10**9
    callback = _queueing_callback(source)
    sent = 200_000
    done = threading.Event()

    def executor() -> None:
        for k in range(sent):
            callback(k)
        done.set()

    taken: list = []
    thread = threading.Thread(target=executor)
    thread.start()
    while not done.is_set():  # the ingest thread drains while the callback appends
        taken.extend(_drained(source.pending))
    thread.join()
    taken.extend(_drained(source.pending))
    assert [msg for _, msg, _ in taken] == list(range(sent))
    stamps = [t for t, _, _ in taken]
    assert stamps == sorted(stamps)  # arrival times taken in the callback
    assert source.queue_dropped == 0 and not source.pending


def test_a_flood_past_the_limit_is_dropped_and_counted():
    source = _Input("response")
    source.read = len
    source.pending_limit = 10
    callback = _queueing_callback(source)
    for k in range(15):
        callback(k)
    queued = _drained(source.pending)
    assert [msg for _, msg, _ in queued] == list(range(10))
    assert all(read is len for _, _, read in queued)  # each message keeps its subscription's read
    assert source.queue_dropped == 5
    callback(99)  # room again once drained
    assert [msg for _, msg, _ in _drained(source.pending)] == [99]
