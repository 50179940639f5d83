"""The node's Foxglove WebSocket server (``foxglove_port`` > 0): the dashboard channels of
``dashboard`` served in-process by the Foxglove SDK, so Foxglove connects without
``foxglove_bridge``. No rclpy here.

Publishing never blocks the caller: ``publish`` appends to a bounded queue that a thread of
its own hands to the SDK (which sends to each client from its own threads, dropping the oldest
message for a client that reads too slowly). A client that subscribes gets the latest message
of that channel at once (the SDK keeps none), so a late dashboard shows the model before the
next solve. Client misbehaviour (malformed frames, subscriptions to unknown channels, floods)
is answered by the SDK with a status message and never raised; it is counted here, from the
SDK's log records and its subscribe callbacks, for ``/diagnostics``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable

from ..errors import UsageError
from .dashboard import CHANNELS, dashboard_topic

QUEUE = 256  # payloads waiting for the publishing thread; beyond, the oldest are dropped (counted)
RESEND_PERIOD = 0.2  # s: a subscribe flood resends the latest messages at most this often


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
    """The Foxglove WebSocket server with one JSON channel per dashboard channel."""

    def __init__(self, host: str, port: int, node_name: str, warn: Callable[[str], None]) -> None:
        import foxglove  # imported here: only a node with foxglove_port > 0 needs the SDK

        self.warn = warn
        self.counts = dict.fromkeys(("foxglove_connections", "foxglove_disconnections", "foxglove_subscribe_requests",
                                     "foxglove_unsubscribe_requests", "foxglove_invalid_frames",
                                     "foxglove_client_errors", "foxglove_queue_dropped", "foxglove_sent"), 0)
        self._subscriptions: set[tuple[int, int]] = set()  # (client id, channel id)
        self._log = _LogCounter(self)
        logger = logging.getLogger("foxglove")
        logger.setLevel(logging.INFO)
        logger.propagate = False  # counted and reported by the node, not printed per frame
        logger.addHandler(self._log)
        self._context = foxglove.Context()
        self._channels = {}
        for name, (schema_name, schema) in CHANNELS.items():
            schema_bytes = json.dumps(schema).encode()
            self._channels[name] = foxglove.Channel(
                dashboard_topic(name, node_name), message_encoding="json", context=self._context,
                schema=foxglove.Schema(name=schema_name, encoding="jsonschema", data=schema_bytes))
        self._by_id = {channel.id(): name for name, channel in self._channels.items()}
        try:
            self._server = foxglove.start_server(name=node_name, host=host, port=port, context=self._context,
                                                 server_listener=self)
        except Exception as exc:  # e.g. the port is taken, or the host is not an address of this machine
            logger.removeHandler(self._log)
            raise UsageError(f"foxglove_port: cannot listen on {host}:{port} ({exc})") from None
        self._queue: deque[tuple[str, dict, int]] = deque()
        self._latest: dict[str, tuple[dict, int]] = {}
        self._resend: set[str] = set()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hammer_ros_foxglove", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The port the server listens on (the chosen one when started with port 0)."""
        return self._server.port

    def publish(self, items: list[tuple[str, dict]], stamp_s: float) -> None:
        """Queue (channel, JSON message) pairs; returns at once."""
        log_time = max(0, round(stamp_s * 1e9))
        with self._lock:
            for name, message in items:
                if len(self._queue) >= QUEUE:
                    self._queue.popleft()
                    self.counts["foxglove_queue_dropped"] += 1
                self._queue.append((name, message, log_time))
        self._wake.set()

    def diagnostics(self) -> dict[str, int]:
        """The counters for /diagnostics (plus the current clients' subscriptions)."""
        return {**self.counts, "foxglove_subscriptions": len(self._subscriptions)}

    # ServerListener callbacks (called from the SDK's threads)
    def on_subscribe(self, client, channel) -> None:
        self.counts["foxglove_subscribe_requests"] += 1
        self._subscriptions.add((client.id, channel.id))
        name = self._by_id.get(channel.id)
        if name is not None:
            with self._lock:
                self._resend.add(name)
            self._wake.set()

    def on_unsubscribe(self, client, channel) -> None:
        self.counts["foxglove_unsubscribe_requests"] += 1
        self._subscriptions.discard((client.id, channel.id))

    def _run(self) -> None:
        last_resend = 0.0
        while not self._stop.is_set():
            self._wake.wait(RESEND_PERIOD)
            self._wake.clear()
            with self._lock:
                items, self._queue = list(self._queue), deque()
                resend = set()
                if self._resend and time.monotonic() - last_resend >= RESEND_PERIOD:
                    resend, self._resend = self._resend, set()
            for name, message, log_time in items:
                self._latest[name] = (message, log_time)
                self._send(name, message, log_time)
            if resend:
                last_resend = time.monotonic()
                for name in resend - {name for name, _, _ in items}:
                    if name in self._latest:
                        self._send(name, *self._latest[name])

    def _send(self, name: str, message: dict, log_time: int) -> None:
        try:
            self._channels[name].log(message, log_time=log_time)
            self.counts["foxglove_sent"] += 1
        except Exception as exc:  # (e.g. a value json cannot encode) one message lost, never the node
            self.counts["foxglove_client_errors"] += 1
            self.warn(f"foxglove channel {name}: {type(exc).__name__}: {exc}")

    def stop(self) -> None:
        """Stop the publishing thread and the server (clients are disconnected)."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=1.0)
        self._server.stop()
        logging.getLogger("foxglove").removeHandler(self._log)
