"""The node's inputs: one ``_Input`` per stream of a channel (its subscription, field path and
the queue from the subscription's callback to the channel's ingest thread), and the callbacks
that queue messages: ``_queueing_callback`` for a topic one input reads, ``_fanout_callback`` and
``SharedTopic`` for a topic several inputs read (subscribed once, decoded once per message).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from .environment import prepare_ros_environment

prepare_ros_environment()

from rclpy.event_handler import QoSSubscriptionEventType, UnsupportedEventTypeError  # noqa: E402
from rclpy.exceptions import InvalidHandle  # noqa: E402
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402

from ..messages.cdr import TopicDecoder  # noqa: E402
from ..messages.field_path import FieldPath, extract_samples, message_stamp  # noqa: E402

ARRIVALS = 6  # arrival times of zero-stamped messages kept per stream to tell a sparse stream (``ingest``)


class _Input:
    """One input stream: its subscription, message type and field path."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.subscription = None
        self.path: FieldPath | None = None
        self.raw = None  # cdr.raw_extractor(type, path): samples and stamp from serialized messages
        self.read = None  # message (serialized or built by rclpy) -> (samples, header stamp or 0.0)
        self.message_samples = 1  # samples of the last message read: what a queued message counts
        self.pending: deque = deque()  # (receive time, message, read) from the callback to the ingest thread
        self.pending_limit = 1  # messages the queue takes: max_pending / message_samples
        self.field_errors = 0
        self.last_error = ""
        self.queue_dropped = 0  # messages dropped because the queue to the engine was full (max_pending)
        self._lost_status = None  # the subscription's message-lost status, read by ``dds_lost``
        self._lost_before = 0  # messages lost by the subscriptions before this one
        self.wrong_type = ""  # publishers of another type on the topic (their messages never arrive)
        self.shared: _Input | None = None  # the subscription of a topic read by several channels (several readers)
        self.feed = None  # SharedTopic: its decoded chunks come into ``pending`` (``_decoded``)
        self.headed = False  # the message type has a std_msgs/Header: a zero stamp there is a missing stamp
        self.zero_stamps = 0  # messages with a header stamp of zero
        self.arrivals: deque = deque(maxlen=ARRIVALS)  # receive times of the last zero-stamped messages
        self.arrival_map = (np.empty(0), np.empty(0))  # (receive times, stamps of their last samples): last flush
        self.by_arrival: list[tuple[int, int, float]] = []  # (start, samples, receive time) placed at the flush's end

    def subscribe(self, node, cls, topic: str, callback: Callable, qos: QoSProfile, raw: bool) -> None:
        """(Re)subscribe. The middleware's message-lost status is read when asked (``dds_lost``),
        never taken as an event: the EventsExecutor takes each message-lost event in the thread
        that takes the messages, so once losses begin the messages wait behind them (at 60 000
        Float64 messages/s per topic, 3 of 6 runs lost 42-74 % of the samples with that thread
        found in the event handler's take; none of 6 with the status read here)."""
        self.unsubscribe(node)
        self.subscription = node.create_subscription(cls, topic, callback, qos, raw=raw)
        try:
            with self.subscription.handle:
                self._lost_status = _rclpy.EventHandle(self.subscription.handle,
                                                       QoSSubscriptionEventType.RCL_SUBSCRIPTION_MESSAGE_LOST)
        except UnsupportedEventTypeError:  # a middleware without the status: counted as 0
            self._lost_status = None

    def unsubscribe(self, node) -> None:
        if self.subscription is None:
            return
        self._lost_before = self.dds_lost()
        if self._lost_status is not None:
            self._lost_status.destroy_when_not_in_use()
            self._lost_status = None
        node.destroy_subscription(self.subscription)
        self.subscription = None

    def dds_lost(self) -> int:
        """Messages the middleware reports lost before the callback, over all subscriptions."""
        if self.shared is not None:
            return self.shared.dds_lost()
        status = self._lost_status
        if status is None:
            return self._lost_before
        try:
            with status:
                return self._lost_before + status.take_event().total_count
        except InvalidHandle:  # destroyed meanwhile (deactivate)
            return self._lost_before

    def dropped(self) -> int:
        """Messages dropped because a queue to the engine was full (its own, the shared topic's)."""
        return self.queue_dropped + (self.shared.queue_dropped if self.shared is not None else 0)

    def publishers(self) -> int:
        """Publishers matched with the subscription (0 when unsubscribed): the middleware delivers
        only their messages, so 0 while a publisher is still being discovered or has a QoS that
        cannot match."""
        if self.shared is not None:
            return self.shared.publishers()
        try:
            return self.subscription.get_publisher_count() if self.subscription is not None else 0
        except InvalidHandle:  # destroyed meanwhile (deactivate): none
            return 0


def _queueing_callback(source: _Input) -> Callable[[Any], None]:
    """The subscription callback of ``source``: queue the message with its arrival time and the
    subscription's ``read``, nothing more. The executor thread is what limits the node's message
    rate, so the samples are read from the message (raw CDR or rclpy's message) in the ingest
    thread, and the callback is one closure over a deque (thread-safe appends, no lock; 0.14 us a
    message here against 0.36 us for a method behind a lambda taking a lock). The queue is bounded
    at max_pending samples, a message counted at the size of its stream's last one."""
    queue, read, now = source.pending, source.read, time.time

    def on_message(msg) -> None:
        if len(queue) < source.pending_limit:
            queue.append((now(), msg, read))
        else:  # a flood is dropped
            source.queue_dropped += 1

    return on_message


def built_reader(path: FieldPath) -> Callable[[Any], tuple]:
    """``read`` of messages built by rclpy: (samples at ``path``, header stamp or 0.0)."""
    return lambda msg: (extract_samples(msg, path), message_stamp(msg) or 0.0)


def _drained(queue: deque) -> list:
    """What ``queue`` holds now, taken out (the callback may append meanwhile)."""
    return [queue.popleft() for _ in range(len(queue))]


def _fanout_callback(sources: list[_Input]):
    """The callback of a topic read by ``sources`` (inputs of several channels): the message,
    with its arrival time, queued for each (``_queueing_callback`` for one)."""
    now = time.time

    def on_message(msg) -> None:
        received = now()
        for source in sources:
            if len(source.pending) < source.pending_limit:
                source.pending.append((received, msg, source.read))
            else:
                source.queue_dropped += 1

    return on_message


class SharedTopic:
    """A topic whose every reader takes one number per message (``cdr.TopicDecoder``): the
    subscription's callback queues each serialized message once (``_queueing_callback``), and
    ``distribute`` decodes what is queued for all of them at once, each input getting its
    chunk (receive times, values, bad, header stamps, why bad) for ``ingest.Ingest._decoded``."""

    def __init__(self, topic: str, sources: list[_Input], decoder: TopicDecoder) -> None:
        self.input = _Input(topic)
        self.input.pending_limit = min(s.pending_limit for s in sources)  # one sample a message
        self.sources, self.decoder = sources, decoder
        self._lock = threading.Lock()  # one decode at a time: the chunks keep the messages' order

    def distribute(self) -> None:
        with self._lock:
            items = _drained(self.input.pending)
            if not items:
                return
            receives, messages, _ = zip(*items)
            decoded = self.decoder.decode(list(messages))
            times = np.array(receives)
            for j, source in enumerate(self.sources):
                source.pending.append((times, decoded.values[:, j], decoded.bad[:, j], decoded.stamps,
                                       decoded.errors[j]))
