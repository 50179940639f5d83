"""The node's Foxglove WebSocket server (``foxglove_port`` > 0): the dashboard channels of
``dashboard`` served in-process by the Foxglove SDK, so Foxglove connects without
``foxglove_bridge``, with the node's parameters (get and set, Parameters panel) and its Trigger
services ``~/reset``, ``~/solve``, ``~/diagnose`` (Service Call panel). No rclpy here.

Publishing never blocks the caller: ``publish`` appends to a bounded queue that a thread of
its own hands to the SDK (which sends to each client from its own threads, dropping the oldest
message for a client that reads too slowly). A client that subscribes gets the latest message
of that channel at once (the SDK keeps none), so a late dashboard shows the model before the
next solve; that message goes to the subscribing client only (its own sink of the SDK, see
``client_sink``), never again to the others. Client misbehaviour (malformed frames,
subscriptions to unknown channels, floods) is answered by the SDK with a status message and
never raised; it is counted here, from the SDK's log records and its subscribe callbacks, for
``/diagnostics``.

Parameters: ``getParameters`` answers with the node's parameters by name (all for an empty
list); ``setParameters`` sets each one as the ROS SetParameters service does (the node's own
validation); a refused change keeps the value, and its reason (the ROS reason) goes out as a
warning status. A change from any side (``ros2 param set`` too) goes out to the clients that
subscribed to parameter updates (``parameters_changed``, sent by the server's thread).
Services: JSON requests (``{}``) and responses ``{"success": bool, "message": str}``, the
std_srvs/srv/Trigger fields.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

from ..errors import UsageError
from ..messages.dashboard import CHANNELS, channel_node, dashboard_topic
from ..messages.outputs import checked_ns

QUEUE = 256  # payloads waiting for the publishing thread; beyond, the oldest are dropped (counted)
RESEND_PERIOD = 0.2  # s: a client's subscribe flood resends it the latest messages at most this often
TRIGGER_REQUEST = {"title": "std_srvs/srv/Trigger_Request", "type": "object", "properties": {}}
TRIGGER_RESPONSE = {"title": "std_srvs/srv/Trigger_Response", "type": "object",
                    "properties": {"success": {"type": "boolean"}, "message": {"type": "string"}}}


class NodeParameters(Protocol):
    """What the server needs of the node's parameters."""

    def parameter_values(self) -> dict[str, Any]: ...

    def set_parameter_value(self, name: str, value: Any) -> tuple[bool, str]: ...


Key = tuple[str, str]  # (source: the node's channel or "", dashboard channel name): one channel of the server


def client_sink(client_id: int) -> int:
    """The SDK sink id of a connected client. The SDK (0.30) gives every client a sink of its own
    and draws both ids from process-wide counters at the same moment (``ClientId::next()``,
    ``SinkId::next()`` in its Rust core), but its Python ``Client`` exposes only the client id. In
    a process that opens no other Foxglove sink (no ``foxglove.open_mcap``, no gateway: the node's),
    the two counters move together and the client's sink id is its client id.
    ``test_foxglove_server`` checks it with two clients."""
    return client_id


class _LogCounter(logging.Handler):
    """Counts the SDK's log records about clients (its only report of bad frames)."""

    def __init__(self, server: DashboardServer) -> None:
        super().__init__(logging.INFO)
        self.server = server

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        counts = self.server.counts
        if text.startswith("Registered client"):
            counts["foxglove_connections"] += 1
        elif text.startswith("Unregistered client"):
            counts["foxglove_disconnections"] += 1
        elif record.levelno >= logging.WARNING:
            key = "foxglove_invalid_frames" if "Invalid message" in text else "foxglove_client_errors"
            counts[key] += 1
            self.server.warn(f"foxglove client: {text}")


class DashboardServer:
    """The Foxglove WebSocket server with one JSON channel per dashboard channel, the node's
    ``parameters`` and its Trigger ``services`` (name -> handler returning (success, message)).
    ``sources``: the node's channels (``channels.py``), each with its dashboard channels under
    ``/<node>/<source>/dashboard/``; by default the one source ``""`` (``/<node>/dashboard/``)."""

    def __init__(self, host: str, port: int, node_name: str, warn: Callable[[str], None],
                 parameters: NodeParameters | None = None,
                 services: dict[str, Callable[[], tuple[bool, str]]] | None = None,
                 sources: tuple[str, ...] = ("",)) -> None:
        import foxglove  # imported here: only a node with foxglove_port > 0 needs the SDK
        from foxglove.websocket import Capability

        self.warn = warn
        self._parameters = parameters
        self.counts = dict.fromkeys(("foxglove_connections", "foxglove_disconnections", "foxglove_subscribe_requests",
                                     "foxglove_unsubscribe_requests", "foxglove_invalid_frames",
                                     "foxglove_client_errors", "foxglove_queue_dropped", "foxglove_sent",
                                     "foxglove_resent", "foxglove_parameters_refused"), 0)
        self._subscriptions: set[tuple[int, int]] = set()  # (client id, channel id)
        self._log = _LogCounter(self)
        logger = logging.getLogger("foxglove")
        logger.setLevel(logging.INFO)
        logger.propagate = False  # counted and reported by the node, not printed per frame
        logger.addHandler(self._log)
        self._context = foxglove.Context()
        self._channels = {}  # (source, name) -> its channel
        for source in sources:
            for name, (schema_name, schema) in CHANNELS.items():
                schema_bytes = json.dumps(schema).encode()
                self._channels[(source, name)] = foxglove.Channel(
                    dashboard_topic(name, channel_node(node_name, source)), message_encoding="json",
                    context=self._context,
                    schema=foxglove.Schema(name=schema_name, encoding="jsonschema", data=schema_bytes))
        self._by_id = {channel.id(): key for key, channel in self._channels.items()}
        capabilities = ([Capability.Parameters] if parameters is not None else []) + (
            [Capability.Services] if services else [])
        try:
            self._server = foxglove.start_server(
                name=node_name, host=host, port=port, context=self._context, server_listener=self,
                capabilities=capabilities, supported_encodings=["json"],
                services=[self._service(f"/{node_name}/{name}", handler) for name, handler in (services or {}).items()])
        except Exception as exc:  # e.g. the port is taken, or the host is not an address of this machine
            logger.removeHandler(self._log)
            raise UsageError(f"foxglove_port: cannot listen on {host}:{port} ({exc})") from None
        self._queue: deque[tuple[Key, dict, int]] = deque()
        self._changed_parameters: dict[str, Any] = {}  # to send to the parameter subscribers
        self._latest: dict[Key, tuple[dict, int]] = {}
        # (client id, channel) -> when it subscribed: send it the channel's latest message, unless broadcast since
        self._resend: dict[tuple[int, Key], float] = {}
        self._broadcast: dict[Key, float] = {}  # channel -> when its latest message went to every subscriber
        self._last_resend: dict[int, float] = {}  # client id -> when it was last sent latest messages
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hammer_ros_foxglove", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The port the server listens on (the chosen one when started with port 0)."""
        return self._server.port

    @staticmethod
    def _service(name: str, handler: Callable[[], tuple[bool, str]]):
        import foxglove

        def message_schema(schema: dict) -> foxglove.MessageSchema:
            return foxglove.MessageSchema(encoding="json", schema=foxglove.Schema(
                name=schema["title"], encoding="jsonschema", data=json.dumps(schema).encode()))

        def call(request) -> bytes:
            success, message = handler()
            return json.dumps({"success": bool(success), "message": message}).encode()

        return foxglove.Service(name, schema=foxglove.ServiceSchema(
            "std_srvs/srv/Trigger", request=message_schema(TRIGGER_REQUEST),
            response=message_schema(TRIGGER_RESPONSE)), handler=call)

    def publish(self, items: list[tuple[str, dict]], stamp_ns: int, source: str = "") -> None:
        """Queue (channel, JSON message) pairs of ``source`` stamped ``stamp_ns``; returns at once."""
        log_time = checked_ns(stamp_ns)
        with self._lock:
            for name, message in items:
                if len(self._queue) >= QUEUE:
                    self._queue.popleft()
                    self.counts["foxglove_queue_dropped"] += 1
                self._queue.append(((source, name), message, log_time))
        self._wake.set()

    def parameters_changed(self, values: dict[str, Any]) -> None:
        """Queue changed parameter values for the clients subscribed to them; returns at once (the
        SDK is not called from the parameter callback, which may run inside an SDK callback)."""
        with self._lock:
            self._changed_parameters.update(values)
        self._wake.set()

    def diagnostics(self) -> dict[str, int]:
        """The counters for /diagnostics (plus the current clients' subscriptions)."""
        return {**self.counts, "foxglove_subscriptions": len(self._subscriptions)}

    # ServerListener callbacks (called from the SDK's threads)
    def on_subscribe(self, client, channel) -> None:
        self.counts["foxglove_subscribe_requests"] += 1
        name = self._by_id.get(channel.id)
        with self._lock:
            self._subscriptions.add((client.id, channel.id))
            if name is not None:
                self._resend[(client.id, name)] = time.monotonic()
        self._wake.set()

    def on_unsubscribe(self, client, channel) -> None:
        self.counts["foxglove_unsubscribe_requests"] += 1
        with self._lock:
            self._subscriptions.discard((client.id, channel.id))
            self._resend.pop((client.id, self._by_id.get(channel.id)), None)
            if not any(c == client.id for c, _ in self._subscriptions):  # gone (also on a disconnect)
                self._last_resend.pop(client.id, None)

    def on_get_parameters(self, client, param_names: list[str], request_id: str | None = None) -> list:
        values = self._parameters.parameter_values()
        return [_parameter(name, values[name]) for name in (param_names or values) if name in values]

    def on_set_parameters(self, client, parameters: list, request_id: str | None = None) -> list:
        for parameter in parameters:
            ok, reason = self._parameters.set_parameter_value(parameter.name, parameter.get_value())
            if not ok:
                self.counts["foxglove_parameters_refused"] += 1
                self._server.publish_status(reason, _status_level("Warning"),  # the ROS reason names it
                                            id=f"parameter {parameter.name}")
        values = self._parameters.parameter_values()
        return [_parameter(p.name, values[p.name]) for p in parameters if p.name in values]

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(RESEND_PERIOD)
            self._wake.clear()
            now = time.monotonic()
            with self._lock:
                items, self._queue = list(self._queue), deque()
                changed, self._changed_parameters = self._changed_parameters, {}
                due = {key: self._resend.pop(key) for key in list(self._resend)
                       if now - self._last_resend.get(key[0], -RESEND_PERIOD) >= RESEND_PERIOD}
            for name, message, log_time in items:
                self._latest[name] = (message, log_time)
                self._send(name, message, log_time)
                self._broadcast[name] = time.monotonic()  # after: a client subscribed before has it
            if changed:
                self._server.publish_parameter_values([_parameter(k, v) for k, v in changed.items()])
            for (client_id, name), subscribed in due.items():
                self._last_resend[client_id] = now
                # a message broadcast after the subscription reached this client already
                if name in self._latest and self._broadcast[name] < subscribed:
                    self._send(name, *self._latest[name], sink=client_sink(client_id))

    def _send(self, name: Key, message: dict, log_time: int, sink: int | None = None) -> None:
        try:
            # bytes: the SDK's Channel.log drops sink_id for a dict (0.30.3)
            self._channels[name].log(json.dumps(message, allow_nan=False).encode(), log_time=log_time, sink_id=sink)
            self.counts["foxglove_sent" if sink is None else "foxglove_resent"] += 1
        except Exception as exc:  # (e.g. a value json cannot encode) one message lost, never the node
            self.counts["foxglove_client_errors"] += 1
            self.warn(f"foxglove channel {self._channels[name].topic()}: {type(exc).__name__}: {exc}")

    def stop(self) -> None:
        """Stop the publishing thread and the server (clients are disconnected)."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=1.0)
        self._server.stop()
        logging.getLogger("foxglove").removeHandler(self._log)


def _status_level(name: str):
    import foxglove

    return getattr(foxglove.StatusLevel, name)


def _parameter(name: str, value: Any):
    """A Foxglove parameter of a node parameter's value (floats typed as floats, so that 2.0
    stays a double on the wire; None: a parameter without a value)."""
    import foxglove

    if isinstance(value, float):
        return foxglove.Parameter(name, value=value, type=foxglove.ParameterType.Float64)
    if isinstance(value, (list, tuple)) and value and all(isinstance(x, float) for x in value):
        return foxglove.Parameter(name, value=list(value), type=foxglove.ParameterType.Float64Array)
    return foxglove.Parameter(name, value=list(value) if isinstance(value, tuple) else value)
