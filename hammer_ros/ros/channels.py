"""Several channels in one live node: a ``channels`` list in the node's params file (the form of
``io.bags.config_channels``, as ``replay`` reads it) makes the node identify one (excitation,
response) pair per channel, each with its own ``StreamingEngine``, solve and diagnosis threads
and outputs under ``~/NAME/`` (model, poles, zeros, markov, nonlinearity, diagnosis).

A topic read by several channels is subscribed once and decoded once per message: its callback
queues the serialized message once (``SharedTopic``), and the first channel's ingest thread to
flush reads every channel's number (``position[joint_3]``, ``data[2]``) out of all the queued
messages in one numpy pass (``cdr.TopicDecoder``: the layout, names included, walked once per
distinct layout) and hands each channel its column. A topic where some channel reads what the
decoder does not (a whole array, a field rclpy must build) queues the message (raw CDR when every
channel has a raw extractor, else the message rclpy built once) for every channel, and each
channel's ingest thread takes its own field out. /diagnostics
carries one array with one status per channel (``NODE/NAME: identification``, the newest of
each); ``~/reset``, ``~/solve`` and ``~/diagnose`` act on every channel. The parameters of a
node with several channels are fixed at startup; it has no Foxglove server and no output_mcap.
"""

from __future__ import annotations

import json
import threading
from dataclasses import fields
from typing import Any

import numpy as np

from .environment import prepare_ros_environment

prepare_ros_environment()

from rclpy.lifecycle import LifecycleNode  # noqa: E402

from ..errors import UsageError  # noqa: E402
from ..io.bags import OTHER_KEYS, TOPIC_KEYS, Channel, config_channels  # noqa: E402
from ..streaming.config import EngineConfig  # noqa: E402
from .cdr import TopicDecoder, topic_decoder  # noqa: E402
from .node_core import (  # noqa: E402
    PARAMETERS,
    IdentificationCore,
    _drained,
    _Input,
    _normal_type,
    _queueing_callback,
    built_reader,
    message_class,
)
from .outputs import message_class as output_message_class  # noqa: E402

REPLAY_KEYS = {f.name for f in fields(EngineConfig)} | set(TOPIC_KEYS) | set(OTHER_KEYS)
SOURCE = "params file"


def file_channels(node) -> list[Channel]:
    """The channels of the node's params file ([] without a ``channels`` parameter): its
    parameter overrides as ``config_channels`` reads them (``NAME.key`` per channel); a node-only
    key (solver_process, diagnosis_period, ...) is left to ``ChannelCore``."""
    overrides = {name: p.value for name, p in node._parameter_overrides.items()}
    if not overrides.get("channels"):
        return []
    params = {}
    for key, value in overrides.items():
        head, _, rest = key.partition(".")
        if head == "qos_overrides" or ((rest or key) not in REPLAY_KEYS and (rest or key) in PARAMETERS):
            continue
        params[key] = list(value) if type(value).__name__ == "array" else value
    return config_channels(params, SOURCE)


def channel_values(node, channel: Channel) -> dict[str, Any]:
    """The node parameters ``channel`` sets: its ``params`` (the file's top level with its own
    overrides) and its node-only keys (``NAME.solver_process``, ...) from the node's overrides."""
    section = {k.split(".", 1)[1]: v.value for k, v in node._parameter_overrides.items()
               if k.startswith(f"{channel.name}.")}
    return {k: v for k, v in {**channel.params, **section}.items() if k in PARAMETERS}


class _DiagnosticsPort:
    """What a channel publishes /diagnostics on: its status goes into the node's one array."""

    def __init__(self, merger: DiagnosticsMerger, name: str) -> None:
        self.merger, self.name = merger, name

    def publish(self, message) -> None:
        self.merger.publish(self.name, message)


class DiagnosticsMerger:
    """One /diagnostics publisher for every channel: each array a channel publishes is sent with
    the newest status of every channel (in the params file's order)."""

    def __init__(self, publisher, names: list[str]) -> None:
        self.publisher = publisher
        self._latest: dict[str, Any] = dict.fromkeys(names)
        self._lock = threading.Lock()

    def port(self, name: str) -> _DiagnosticsPort:
        return _DiagnosticsPort(self, name)

    def publish(self, name: str, message) -> None:
        with self._lock:
            self._latest[name] = message.status[0]
            message.status = [s for s in self._latest.values() if s is not None]
            self.publisher.publish(message)


class ChannelCore(IdentificationCore):
    """One channel: an ``IdentificationCore`` on the host node's rclpy API (logger, clock,
    publishers), with the channel's parameter values, outputs under ``~/NAME/`` and inputs that
    the ``ChannelSet`` subscribes."""

    def __init__(self, host, channel: Channel, merger: DiagnosticsMerger) -> None:
        self._host, self.channel, self._merger = host, channel, merger
        self._init_state()
        self._values = {name: host._declared_value(name) for name in PARAMETERS} | channel_values(host, channel)

    def __getattr__(self, name: str):  # the rclpy Node API: the host's
        if name.startswith("__") or "_host" not in self.__dict__:
            raise AttributeError(name)
        return getattr(self.__dict__["_host"], name)

    def _file_channels(self) -> list[Channel]:
        return []  # a channel is one channel

    def get_logger(self):
        return self._host.get_logger().get_child(self.channel.name)

    def configure(self) -> None:
        where = f"{SOURCE}: channel {self.channel.name!r}"
        for name in ("foxglove_port", "output_mcap"):
            if self._values[name]:
                raise UsageError(f"{where}: {name}: not supported with several channels (one channel or none only)")
        try:
            super().configure()
        except UsageError as exc:
            raise UsageError(f"{where}: {exc}") from None

    def _declared_value(self, name: str) -> Any:
        return self._values[name]

    def _status_name(self) -> str:
        return f"{self._host.get_name()}/{self.channel.name}"

    def _create_output_publisher(self, cls, topic: str, qos):
        if topic == "/diagnostics":
            return self._merger.port(self.channel.name)
        return self._host._create_output_publisher(cls, topic.replace("~/", f"~/{self.channel.name}/", 1), qos)

    def _destroy_output_publisher(self, publisher) -> None:
        if not isinstance(publisher, _DiagnosticsPort):
            self._host._destroy_output_publisher(publisher)

    def _subscribe(self, stream: str) -> None:
        """Only made ready: ``ChannelSet.activate`` subscribes each topic once for every channel."""
        self._prepare_input(stream)


def _fanout_callback(sources: list[_Input]):
    """The callback of a topic read by ``sources`` (inputs of several channels): the message,
    with its arrival time, queued for each (``node_core._queueing_callback`` for one)."""
    from time import time as now

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
    chunk (receive times, values, bad, header stamps, why bad) for ``IdentificationCore._decoded``."""

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


class ChannelSet:
    """The channels of a node (``IdentificationCore.configure`` with several ``channels``): one
    ``ChannelCore`` each, configured at once (a bad channel is a UsageError naming it)."""

    def __init__(self, host, channels: list[Channel]) -> None:
        if isinstance(host, LifecycleNode):
            raise UsageError(f"{SOURCE}: channels: several channels need the unmanaged node (without --managed)")
        self.host = host
        self.merger = DiagnosticsMerger(
            host._create_output_publisher(output_message_class("diagnostic_msgs/msg/DiagnosticArray"),
                                          "/diagnostics", 10), [c.name for c in channels])
        self.cores = [ChannelCore(host, channel, self.merger) for channel in channels]
        self.topics: list[_Input] = []  # the shared subscriptions, one per topic
        try:
            for core in self.cores:
                core.configure()
        except BaseException:
            self.cleanup()
            raise
        host.get_logger().info(f"identifying {len(self.cores)} channels: " + ", ".join(
            f"{c.channel.name} ({c.channel.excitation} -> {c.channel.response}, {c.values['method']})"
            for c in self.cores))

    def activate(self) -> None:
        """Start every channel, then subscribe each topic once for all the channels reading it."""
        for core in self.cores:
            core.activate()
        readers: dict[tuple[str, str], list[tuple[ChannelCore, str]]] = {}
        for core in self.cores:
            for stream in core._streams():
                key = (core.values[f"{stream}_topic"], _normal_type(core.values[f"{stream}_type"]))
                readers.setdefault(key, []).append((core, stream))
        for (topic, type_name), users in readers.items():
            sources = [core.inputs[stream] for core, stream in users]
            cls = message_class(type_name)
            decoder = topic_decoder(cls, [s.path for s in sources])
            raw = decoder is not None or all(s.raw is not None for s in sources)
            if decoder is not None:
                feed = SharedTopic(topic, sources, decoder)
                shared, callback = feed.input, _queueing_callback(feed.input)
            else:
                feed, shared, callback = None, _Input(topic), _fanout_callback(sources)
            core, stream = users[0]
            qos = core._prepare_input(stream)[2]  # (before: it sets the first input's read)
            if not raw:  # rclpy builds the message once; every channel reads its field from it
                for source in sources:
                    source.read = built_reader(source.path)
            shared.subscribe(self.host, cls, topic, callback, qos, raw=raw)
            for source in sources:
                source.shared, source.feed = shared, feed
            self.topics.append(shared)
        self.host.active = True

    def deactivate(self, publish: bool = True) -> None:
        self.host.active = False
        for shared in self.topics:
            shared.unsubscribe(self.host)
        self.topics = []
        for core in self.cores:
            core.deactivate(publish)

    def cleanup(self) -> None:
        for core in self.cores:
            core.cleanup()
        if self.merger.publisher is not None:
            self.host._destroy_output_publisher(self.merger.publisher)
            self.merger.publisher = None

    def close(self) -> None:
        """Stop ingesting, solve every channel once more (its final model on stderr), release."""
        if self.host.active:
            self.deactivate(publish=False)
        for core in self.cores:
            if core.engine is not None:
                core.finish()
        self.cleanup()

    def each(self, service: str) -> tuple[bool, str]:
        """A Trigger service (reset_window, solve_now, diagnose_now) of every channel: success
        when every channel succeeded; the message a JSON object NAME -> the channel's answer (its
        JSON, else {"error": why})."""
        answers = {}
        success = True
        for core in self.cores:
            ok, message = getattr(core, service)()
            success &= ok
            try:
                answers[core.channel.name] = json.loads(message) if ok else {"error": message}
            except json.JSONDecodeError:  # ~/reset answers in words
                answers[core.channel.name] = {"message": message}
        return success, json.dumps(answers, allow_nan=False)


class ChannelSupport:
    """The node classes' ``channels`` hooks of ``IdentificationCore.configure``: the params file's
    channels (``file_channels``), a ``ChannelSet`` for several, one channel's parameters."""

    def _file_channels(self) -> list[Channel]:
        return file_channels(self)

    def _channel_set(self, channels: list[Channel]) -> ChannelSet:
        return ChannelSet(self, channels)

    def _channel_values(self, channel: Channel) -> dict[str, Any]:
        return channel_values(self, channel)
