"""A Foxglove WebSocket client for the tests (``websockets``, subprotocol foxglove.sdk.v1) in a
thread of its own, recording what a live node's server sends; and a free TCP port."""

from __future__ import annotations

import asyncio
import json
import struct
import threading

SUBPROTOCOL = "foxglove.sdk.v1"


class FoxgloveClient:
    """A Foxglove WebSocket client in a thread of its own (asyncio), recording what it receives."""

    def __init__(self, port: int, subscribe: tuple[str, ...], first_frames: tuple[dict, ...] = ()) -> None:
        self.port, self.wanted, self.first_frames = port, subscribe, first_frames
        self.parameter_values: list[dict] = []  # parameterValues messages
        self.info: dict | None = None
        self.channels: dict[str, dict] = {}
        self.messages: dict[str, list[dict]] = {topic: [] for topic in subscribe}
        self.log_times: dict[str, list[int]] = {topic: [] for topic in subscribe}
        self.statuses: list[dict] = []
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self._thread.start()

    async def _run(self) -> None:
        import websockets

        try:
            async with websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=[SUBPROTOCOL]) as ws:
                by_subscription: dict[int, str] = {}
                while not self._stop.is_set():
                    try:
                        frame = await asyncio.wait_for(ws.recv(), 0.1)
                    except asyncio.TimeoutError:
                        continue
                    if isinstance(frame, bytes):  # opcode 1: message data
                        assert frame[0] == 1
                        subscription, log_time = struct.unpack_from("<IQ", frame, 1)
                        self.messages[by_subscription[subscription]].append(json.loads(frame[13:]))
                        self.log_times[by_subscription[subscription]].append(log_time)
                        continue
                    doc = json.loads(frame)
                    if doc["op"] == "serverInfo":
                        for first in self.first_frames:
                            await ws.send(json.dumps(first))
                        self.info = doc
                    elif doc["op"] == "parameterValues":
                        self.parameter_values.append(doc)
                    elif doc["op"] == "advertise":
                        self.channels.update({c["topic"]: c for c in doc["channels"]})
                        subscriptions = []
                        for k, topic in enumerate(self.wanted, start=1):
                            if topic in self.channels and topic not in by_subscription.values():
                                by_subscription[k] = topic
                                subscriptions.append({"id": k, "channelId": self.channels[topic]["id"]})
                        if subscriptions:
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
                    elif doc["op"] == "status":
                        self.statuses.append(doc)
        except BaseException as exc:  # reported by the test
            self.error = exc

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
