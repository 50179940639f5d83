"""The channels of a node: N >= 1 ``IdentificationChannel``s (one is the case N = 1: the node's
parameters, outputs under ``~/``, its status named after the node, parameters settable live);
several come from a ``channels`` list in the node's params file (the form of
``io.bag_config.config_channels``, as ``replay`` reads it), each with its own engine, solve and
diagnosis threads and outputs under ``~/NAME/`` (model, poles, zeros, markov, nonlinearity,
diagnosis), their parameters fixed at startup.

The inputs of one stream (excitation, response, reference) of several channels on one topic
share one subscription (one channel: one subscription per stream), and the topic is decoded once
per message: its callback queues the serialized message once (``SharedTopic``), and the first channel's ingest thread to
flush reads every channel's number (``position[joint_3]``, ``data[2]``) out of all the queued
messages in one numpy pass (``cdr.TopicDecoder``) and hands each channel its column. A topic where
some reader takes what the decoder does not (a whole array, a field rclpy must build) queues the
message (raw CDR when every reader has a raw extractor, else the message rclpy built once) for
every reader. /diagnostics carries one array with one status per channel (the newest of each);
``~/reset``, ``~/solve`` and ``~/diagnose`` act on every channel. ``foxglove_port``,
``foxglove_host`` and ``output_mcap`` are the node's: one Foxglove server carries every channel's
dashboard channels (under ``/<node>/NAME/dashboard/`` for several), one output_mcap file every
channel's results.
"""

from __future__ import annotations

import json
import threading
from typing import TYPE_CHECKING, Any

from .environment import prepare_ros_environment

prepare_ros_environment()

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from ..messages.outputs import OUTPUT_TOPICS  # noqa: E402
from ..messages.types import normal_type  # noqa: E402
from .channel import IdentificationChannel, Recorder  # noqa: E402
from .inputs import SharedTopic, _fanout_callback, _Input, _queueing_callback, built_reader  # noqa: E402
from .message_types import message_class as output_message_class  # noqa: E402
from .message_types import topic_decoder  # noqa: E402
from .parameters import NODE_WIDE, REFERENCE, STREAMS, coerce  # noqa: E402
from .workers import NodeWorkers  # noqa: E402

if TYPE_CHECKING:
    from .foxglove_server import DashboardServer

DIAGNOSIS_TYPE = "std_msgs/msg/String"


class _ServerPort:
    """What a channel sends its dashboard channels to: the node's Foxglove server, as its source
    NAME ("" for the only channel)."""

    def __init__(self, server: DashboardServer, name: str) -> None:
        self.server, self.name = server, name

    @property
    def port(self) -> int:
        return self.server.port

    def publish(self, items: list[tuple[str, dict]], stamp_ns: int) -> None:
        self.server.publish(items, stamp_ns, self.name)

    def diagnostics(self) -> dict[str, int]:
        return self.server.diagnostics()


class _DiagnosticsPort:
    """What a channel publishes /diagnostics on: its status goes into the node's one array."""

    def __init__(self, merger: DiagnosticsMerger, name: str) -> None:
        self.merger, self.name = merger, name

    def publish(self, message) -> None:
        self.merger.publish(self.name, message)


class DiagnosticsMerger:
    """One /diagnostics publisher for every channel: each array a channel publishes is sent with
    the newest status of every channel (in the channels' order)."""

    def __init__(self, publisher, names: list[str]) -> None:
        self.publisher = publisher
        self._latest: dict[str, Any] = dict.fromkeys(names)
        self._lock = threading.Lock()

    def publish(self, name: str, message) -> None:
        with self._lock:
            self._latest[name] = message.status[0]
            message.status = [s for s in self._latest.values() if s is not None]
            self.publisher.publish(message)


class ChannelSet:
    """The channels of a configured node, built from ``values`` (name -> coerced parameter values;
    one entry named "" for the node's only channel) on ``host`` (``node_core.NodeHost``: the rclpy
    node's publishers, subscriptions, parameters and services). ``node_core.NodeHost.configure``
    has checked the values."""

    def __init__(self, host, values: dict[str, dict[str, Any]], node_wide: dict[str, Any]) -> None:
        self.host, self.node = host, host.node
        self.single = list(values) == [""]
        self.active = False
        self.topics: dict[tuple[str, str, str], _Input] = {}  # (topic, type, stream) -> its subscription
        self.server: DashboardServer | None = None
        self.channels: list[IdentificationChannel] = []
        self.merger = DiagnosticsMerger(host.create_output(output_message_class("diagnostic_msgs/msg/DiagnosticArray"),
                                                           "/diagnostics", 10), list(values))
        self.recorder = Recorder("")
        self.workers = NodeWorkers(False)
        try:
            self.workers = NodeWorkers(any(v["solver_process"] for v in values.values()))
            wide = {name: coerce(name, node_wide[name]) for name in NODE_WIDE}
            if wide["foxglove_port"]:
                from .foxglove_server import DashboardServer  # the SDK only when asked for

                self.server = DashboardServer(wide["foxglove_host"], wide["foxglove_port"], self.node.get_name(),
                                              host.warn_throttled, parameters=host,
                                              services=host.trigger_services.handlers, sources=tuple(values))
            self.recorder = Recorder(wide["output_mcap"])
            for name, channel_values in values.items():
                self.channels.append(self._channel(name, channel_values))
        except BaseException:
            self.cleanup()
            raise
        serving = f"; Foxglove on ws://{wide['foxglove_host']}:{self.server.port}" if self.server else ""
        if self.single:
            v = self.channels[0].values
            self.node.get_logger().info(
                f"identifying {v['excitation_topic']}:{v['excitation_field']} -> "
                f"{v['response_topic']}:{v['response_field']} with {v['method']} "
                f"(order {v['order']}, delay {v['delay']}, window {v['window']}){serving}")
        else:
            self.node.get_logger().info(f"identifying {len(self.channels)} channels: " + ", ".join(
                f"{c.name} ({c.values['excitation_topic']} -> {c.values['response_topic']}, {c.values['method']})"
                for c in self.channels) + serving)

    def _channel(self, name: str, values: dict[str, Any]) -> IdentificationChannel:
        """One channel: its publishers under ``~/NAME/`` (``~/`` for the only one), its share of
        /diagnostics, the server and the recorder."""
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        prefix = f"~/{name}/" if name else "~/"
        outputs: dict[str, Any] = {"/diagnostics": _DiagnosticsPort(self.merger, name)}
        try:
            for topic, type_name in [*OUTPUT_TOPICS, ("~/diagnosis", DIAGNOSIS_TYPE)]:
                if topic == "/diagnostics":
                    continue
                qos = latched if topic in ("~/model", "~/diagnosis") else 10
                outputs[topic] = self.host.create_output(output_message_class(type_name),
                                                         topic.replace("~/", prefix, 1), qos)
            logger = self.node.get_logger().get_child(name) if name else self.node.get_logger()
            status = f"{self.node.get_name()}/{name}" if name else self.node.get_name()
            server = None if self.server is None else _ServerPort(self.server, name)
            return IdentificationChannel(name, values, self.node, logger, outputs, server, self.recorder,
                                         self.host.errors, status, self.workers)
        except BaseException:
            for topic, publisher in outputs.items():
                if topic != "/diagnostics":
                    self.host.destroy_output(publisher)
            raise

    def activate(self) -> None:
        """Start every channel, then subscribe each topic once for all the inputs reading it."""
        self.workers.wait_ready(self.node.get_logger())
        for channel in self.channels:
            channel.start()
        self._subscribe()
        self.active = True

    def _subscribe(self, streams: tuple[str, ...] = (*STREAMS, REFERENCE)) -> None:
        """Subscribe the inputs of ``streams``: the inputs of one stream (excitation, response or
        reference) of every channel on one topic share one subscription."""
        readers: dict[tuple[str, str, str], list[tuple[IdentificationChannel, str]]] = {}
        for channel in self.channels:
            for stream in channel.streams():
                if stream in streams:
                    key = (channel.values[f"{stream}_topic"], normal_type(channel.values[f"{stream}_type"]), stream)
                    readers.setdefault(key, []).append((channel, stream))
        for key, users in readers.items():
            topic = key[0]
            prepared = [channel.ingest.prepare(stream) for channel, stream in users]
            sources = [source for source, _, _ in prepared]
            cls, qos = prepared[0][1], prepared[0][2]
            decoder = topic_decoder(cls, [s.path for s in sources]) if len(sources) > 1 else None
            raw = decoder is not None or all(s.raw is not None for s in sources)
            if len(sources) == 1:
                shared, feed = sources[0], None
                shared.shared = shared.feed = None
                callback = _queueing_callback(shared)
            elif decoder is not None:
                feed = SharedTopic(topic, sources, decoder)
                shared, callback = feed.input, _queueing_callback(feed.input)
            else:
                feed, shared, callback = None, _Input(topic), _fanout_callback(sources)
            if not raw:  # rclpy builds the message once; every reader reads its field from it
                for source in sources:
                    source.read = built_reader(source.path)
            shared.subscribe(self.node, cls, topic, callback, qos, raw=raw)
            if len(sources) > 1:
                for source in sources:
                    source.shared, source.feed = shared, feed
            self.topics[key] = shared

    def _unsubscribe(self, streams: tuple[str, ...] = (*STREAMS, REFERENCE)) -> None:
        for key in [k for k in self.topics if k[2] in streams]:
            self.topics.pop(key).unsubscribe(self.node)

    def deactivate(self, publish: bool = True) -> None:
        self.active = False
        self._unsubscribe()
        for channel in self.channels:
            channel.halt(publish)

    def cleanup(self) -> None:
        """Release everything the set built (the last models are forgotten)."""
        if self.server is not None:
            self.server.stop()
            self.server = None
        self.workers.close()
        for channel in self.channels:
            for topic, publisher in channel._outputs.items():
                if topic != "/diagnostics":
                    self.host.destroy_output(publisher)
        self.channels = []
        self.recorder.close()
        if self.merger.publisher is not None:
            self.host.destroy_output(self.merger.publisher)
            self.merger.publisher = None

    def close(self) -> None:
        """Stop ingesting, solve every channel once more (its final model on stderr; its final
        results in output_mcap, then finished), release."""
        if self.active:
            self.deactivate(publish=False)
        for channel in self.channels:
            channel.finish()
        self.recorder.close()
        self.cleanup()

    def set_values(self, values: dict[str, Any], config, changed: set[str]) -> None:
        """The only channel's checked parameter values, live (``NodeHost``): a changed input
        subscribed anew, the change logged and sent to Foxglove, then a solve."""
        (channel,) = self.channels
        streams = channel.apply(values, config, changed)
        if streams and self.active:
            self._unsubscribe(tuple(streams))
            self._subscribe(tuple(streams))
        if changed:
            self.node.get_logger().info("parameters applied: " + ", ".join(
                f"{k}={values[k]}" for k in sorted(changed)))
            if self.server is not None:
                self.server.parameters_changed({k: values[k] for k in changed})
        channel.wake()

    def each(self, service: str) -> tuple[bool, str]:
        """A Trigger service (reset_window, solve_now, diagnose_now): the only channel's answer; for
        several, success when every channel succeeded and the message a JSON object NAME -> the
        channel's answer (its JSON, else {"error": why})."""
        if self.single:
            return getattr(self.channels[0], service)()
        answers = {}
        success = True
        for channel in self.channels:
            ok, message = getattr(channel, service)()
            success &= ok
            try:
                answers[channel.name] = json.loads(message) if ok else {"error": message}
            except json.JSONDecodeError:  # ~/reset answers in words
                answers[channel.name] = {"message": message}
        return success, json.dumps(answers, allow_nan=False)
