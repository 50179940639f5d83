"""Several channels in one live node: a ``channels`` list in the node's params file (the form of
``io.bag_config.config_channels``, as ``replay`` reads it) makes the node identify one (excitation,
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
node with several channels are fixed at startup. ``foxglove_port``, ``foxglove_host`` and
``output_mcap`` are the node's (the params file's top level): one Foxglove server carries every
channel's dashboard channels under ``/<node>/NAME/dashboard/`` (``dashboard.foxglove_layout`` has
one tab per channel), and one output_mcap file every channel's results under ``/<node>/NAME/...``,
as ``replay --out`` / ``--dashboard-out`` write them.
"""

from __future__ import annotations

import json
import threading
from dataclasses import fields
from typing import TYPE_CHECKING, Any

import numpy as np

from .environment import prepare_ros_environment

prepare_ros_environment()

from rclpy.lifecycle import LifecycleNode  # noqa: E402

from ..errors import UsageError  # noqa: E402
from ..io.bag_config import OTHER_KEYS, TOPIC_KEYS, Channel, config_channels  # noqa: E402
from ..io.bag_writer import ResultWriter  # noqa: E402
from ..messages.cdr import TopicDecoder  # noqa: E402
from ..streaming.config import EngineConfig  # noqa: E402
from .message_types import message_class as output_message_class  # noqa: E402
from .message_types import topic_decoder  # noqa: E402
from .node_core import (  # noqa: E402
    PARAMETERS,
    IdentificationCore,
    _coerce,
    _drained,
    _Input,
    _normal_type,
    _queueing_callback,
    built_reader,
    close_output_mcap,
    message_class,
)

if TYPE_CHECKING:
    from .foxglove_server import DashboardServer

REPLAY_KEYS = {f.name for f in fields(EngineConfig)} | set(TOPIC_KEYS) | set(OTHER_KEYS)
SOURCE = "params file"
NODE_WIDE = ("foxglove_port", "foxglove_host", "output_mcap")  # one for the node, never per channel


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


class _ServerPort:
    """What a channel sends its dashboard channels to: the node's Foxglove server, as its source
    NAME (``/<node>/NAME/dashboard/...``); stopped by the ``ChannelSet``, not by the channel."""

    def __init__(self, server: DashboardServer, name: str) -> None:
        self.server, self.name = server, name

    @property
    def port(self) -> int:
        return self.server.port

    def publish(self, items: list[tuple[str, dict]], stamp_ns: int) -> None:
        self.server.publish(items, stamp_ns, self.name)

    def diagnostics(self) -> dict[str, int]:
        return self.server.diagnostics()

    def stop(self) -> None:
        pass


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
        """Configure the channel; the node's Foxglove server and output_mcap (``NODE_WIDE``) are
        the ``ChannelSet``'s, attached by ``attach``."""
        where = f"{SOURCE}: channel {self.channel.name!r}"
        for name in NODE_WIDE:
            if self._values[name] != self._host._declared_value(name):
                raise UsageError(f"{where}: {name}: one for the node and every channel: set it at the top level")
        self._values |= {"foxglove_port": 0, "output_mcap": ""}
        try:
            super().configure()
        except UsageError as exc:
            raise UsageError(f"{where}: {exc}") from None

    def attach(self, server: DashboardServer | None, writer: ResultWriter | None, writer_lock) -> None:
        """Send the dashboard channels to the node's server (under ``/<node>/NAME/dashboard/``)
        and record the results in the node's output_mcap (under ``/<node>/NAME/``)."""
        self.server = None if server is None else _ServerPort(server, self.channel.name)
        self._writer, self._writer_lock = writer, writer_lock

    def _close_writer(self) -> None:
        self._writer = None  # the node's: ``ChannelSet.close`` finishes it after every channel's final solve

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
        self.server: DashboardServer | None = None
        self.writer: ResultWriter | None = None
        self.writer_lock = threading.Lock()
        try:
            for core in self.cores:
                core.configure()
            self._start_outputs()
        except BaseException:
            self.cleanup()
            raise
        serving = f"; Foxglove on ws://{self.server_host}:{self.server.port}" if self.server else ""
        host.get_logger().info(f"identifying {len(self.cores)} channels: " + ", ".join(
            f"{c.channel.name} ({c.channel.excitation} -> {c.channel.response}, {c.values['method']})"
            for c in self.cores) + serving)

    def _start_outputs(self) -> None:
        """The node's Foxglove server (every channel's dashboard channels) and output_mcap file,
        from the params file's top level, attached to every channel."""
        values = {name: _coerce(name, self.host._declared_value(name)) for name in NODE_WIDE}
        self.server_host = values["foxglove_host"]
        if values["foxglove_port"]:
            from .foxglove_server import DashboardServer  # the SDK only when asked for

            self.server = DashboardServer(values["foxglove_host"], values["foxglove_port"], self.host.get_name(),
                                          self.host._warn_throttled, parameters=self.host,
                                          services=self.host.trigger_services.handlers,
                                          sources=tuple(core.channel.name for core in self.cores))
        if values["output_mcap"]:
            self.writer = ResultWriter(values["output_mcap"], "output_mcap")
        for core in self.cores:
            core.attach(self.server, self.writer, self.writer_lock)

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
        if self.server is not None:
            self.server.stop()
            self.server = None
        with self.writer_lock:
            close_output_mcap(self.writer)
            self.writer = None
        if self.merger.publisher is not None:
            self.host._destroy_output_publisher(self.merger.publisher)
            self.merger.publisher = None

    def close(self) -> None:
        """Stop ingesting, solve every channel once more (its final model on stderr; its final
        results in output_mcap, then finished), release."""
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
