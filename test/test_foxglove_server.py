"""The node's in-process Foxglove server (``foxglove_port``), tested with a WebSocket client
that speaks the Foxglove protocol (``websockets``, subprotocol foxglove.sdk.v1) against a
running node on a private graph: server info, channel advertisements, subscribed messages that
match ~/model and follow their schemas, the latest message resent to a subscribing client only,
parameters and services over the protocol, loopback only, and misbehaving clients that never take
the node down."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import struct

import pytest
from foxglove_client import SUBPROTOCOL, FoxgloveClient
from foxglove_js import run_checker
from ros_helpers import Listener, RosProcess, free_port
from schema_check import mismatches

from hammer_ros.messages.dashboard import CHANNELS, dashboard_topic
from hammer_ros.ros.environment import DomainLease, child_environment
from hammer_ros.ros.node_core import PARAMETERS

pytestmark = pytest.mark.ros

RATE = 250.0
PLANT = {"rate": RATE, "seed": 5}
NODE = {"sample_rate": RATE, "order": 3, "delay": 2, "window": 1000, "solve_rate": 4.0, "diagnosis_period": 0.0}
FLOOD = 3000  # subscribe + unsubscribe pairs


def listening_sockets(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every TCP socket in LISTEN state that process ``pid`` holds."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = []
    for table, width in (("tcp", 8), ("tcp6", 32)):
        with open(f"/proc/net/{table}") as rows:
            for row in list(rows)[1:]:
                fields = row.split()
                if fields[3] == "0A" and fields[9] in inodes:  # 0A = LISTEN
                    address, port = fields[1].split(":")
                    if width == 8:
                        address = socket.inet_ntoa(struct.pack("<I", int(address, 16)))
                    found.append((address, int(port, 16)))
    return found


async def _misbehave(port: int) -> None:
    """Malformed frames, a subscribe flood and a disconnect in the middle of a frame."""
    import websockets

    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
        await ws.recv()  # serverInfo
        channels = json.loads(await ws.recv())["channels"]
        model = next(c["id"] for c in channels if c["topic"] == dashboard_topic("model"))
        for frame in ("not json", '{"op": "no such op"}', '{"op": "subscribe"}', b"\x99\x00\x01", b"",
                      json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 999999}]})):
            await ws.send(frame)
        for k in range(FLOOD):
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 100 + k, "channelId": model}]}))
            await ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [100 + k]}))
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": model}]}))
        await ws.recv()  # the server still answers this client
    # a raw client that upgrades, starts a frame of 1000 bytes and disconnects after 10
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 f"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
                 f"Sec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n".encode())
    await writer.drain()
    assert b"101" in await reader.readuntil(b"\r\n")
    writer.write(bytes([0x81, 0xFE]) + struct.pack(">H", 1000) + b"\x00\x00\x00\x00" + b"{" * 10)  # masked text
    await writer.drain()
    writer.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    logs = tmp_path_factory.mktemp("foxglove")
    port = free_port()
    with DomainLease() as lease:
        env = child_environment(lease.domain_id, log_dir=logs / "ros_log")
        plant = RosProcess("hammer_ros.ros.plant_node", PLANT, env, logs / "plant.log")
        node = RosProcess("hammer_ros.ros.node", {**NODE, "foxglove_port": port}, env, logs / "node.log")
        listener = Listener(env)
        try:
            listener.port, listener.process = port, node
            listener.models = listener.subscribe_json("/hammer_ros/model", latched=False)
            listener.diagnostics = listener.subscribe_diagnostics()
            listener.wait_for(lambda: listener.models, what="a model on ~/model")
            yield listener
        finally:
            listener.close()
            codes = (node.stop(signal.SIGINT), plant.stop(signal.SIGINT))
            assert codes == (0, 0), node.output()[-3000:]


def test_a_foxglove_client_gets_the_channels_and_the_model(rig):
    model_topic, poles_topic = dashboard_topic("model"), dashboard_topic("poles")
    client = FoxgloveClient(rig.port, (model_topic, poles_topic))
    try:
        rig.wait_for(lambda: client.error or (client.messages[model_topic] and client.messages[poles_topic]),
                     what="model and poles from the Foxglove server")
        assert client.error is None
        assert client.info["name"] == "hammer_ros"
        assert set(client.channels) == {dashboard_topic(name) for name in CHANNELS}
        model = client.channels[model_topic]
        assert (model["encoding"], model["schemaEncoding"], model["schemaName"]) == ("json", "jsonschema",
                                                                                   "hammer_ros.Model")
        assert all(json.loads(client.channels[dashboard_topic(name)]["schema"]) == schema
                   for name, (_, schema) in CHANNELS.items())
        assert client.channels[dashboard_topic("diagnosis_log")]["schemaName"] == "foxglove.Log"

        def matching():  # a Foxglove model equal to a ~/model message (the same solve)
            ros = {m["stamp"]: m for m in rig.models}
            return [(m, ros[m["stamp"]]) for m in client.messages[model_topic] if m["stamp"] in ros]

        foxglove_model, ros_model = rig.wait_for(matching, what="a Foxglove model that is on ~/model too")[-1]
        assert {k: v for k, v in foxglove_model.items() if k != "timestamp"} == ros_model
        for topic in (model_topic, poles_topic):
            assert all(mismatches(CHANNELS[topic.rsplit("/", 1)[1]][1], m) == [] for m in client.messages[topic])
        poles = client.messages[poles_topic][-1]
        assert len(poles["real"]) == len(poles["imag"]) == NODE["order"]
        assert [p["x"] for p in poles["points"]] == poles["real"] and len(poles["unit_circle"]) > 60
    finally:
        client.close()


async def _resubscribe(port: int, cycles: int) -> tuple[int, int]:
    """Subscribe to every channel, wait for a model, unsubscribe; ``cycles`` times. (Cycles with
    a model, cycles whose model was one this client had already received: a resent latest one.)"""
    import websockets

    received, repeated, seen = 0, 0, set()
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
        await ws.recv()  # serverInfo
        channels = {c["topic"]: c["id"] for c in json.loads(await ws.recv())["channels"]}
        for k in range(cycles):
            ids = {topic: 1000 * k + i for i, topic in enumerate(channels)}
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": ids[topic], "channelId": channel} for topic, channel in channels.items()]}))
            try:  # the latest model (within RESEND_PERIOD), or a fresh one
                while True:
                    frame = await asyncio.wait_for(ws.recv(), 2.0)
                    if not isinstance(frame, bytes):
                        continue
                    subscription, log_time = struct.unpack_from("<IQ", frame, 1)
                    if subscription == ids[dashboard_topic("model")]:
                        received, repeated = received + 1, repeated + (log_time in seen)
                        seen.add(log_time)
                        break
            except asyncio.TimeoutError:
                pass
            await ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": list(ids.values())}))
    return received, repeated


def test_a_resubscribing_client_sends_no_duplicate_to_another(rig):
    """While one client subscribes and unsubscribes 30 times, another dashboard receives each
    message once (the latest message goes to the subscribing client only)."""
    topics = tuple(dashboard_topic(name) for name in CHANNELS if name not in ("diagnosis", "diagnosis_log"))
    watcher = FoxgloveClient(rig.port, topics)
    try:
        rig.wait_for(lambda: watcher.error or all(watcher.messages[t] for t in topics), what="every channel")
        resent = rig.wait_for(lambda: rig.diagnostics and int(rig.diagnostics[-1]["foxglove_resent"]) + 1,
                              what="the server's counters") - 1
        received, repeated = asyncio.run(asyncio.wait_for(_resubscribe(rig.port, 30), 120))
        assert received == 30 and repeated >= 3  # a model every time, often (11 of 30 here) the resent latest
        rig.wait_for(lambda: int(rig.diagnostics[-1]["foxglove_resent"]) >= resent + 30,  # most cycles, every channel
                     what="the latest messages resent to the resubscribing client")
        assert watcher.error is None
        for topic in topics:
            times = watcher.log_times[topic]
            assert len(times) == len(set(times)) and len(times) >= 2, topic  # no message twice
            schema = CHANNELS[topic.rsplit("/", 1)[1]][1]
            assert all(mismatches(schema, m) == [] for m in watcher.messages[topic]), topic  # every key declared
    finally:
        watcher.close()


async def _parameters_and_services(port: int) -> dict:
    """getParameters, an accepted and a refused setParameters and a ~/solve call; what came back."""
    import websockets

    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
        seen: dict = {"status": []}

        async def until(key: str, done=None):
            """Read frames until ``key`` was seen (or ``done()``); what came with it."""
            while not (done() if done else key in seen):
                frame = await asyncio.wait_for(ws.recv(), 30)
                if isinstance(frame, bytes):
                    if frame[0] == 3:  # service call response: service id, call id, encoding, payload
                        service, call, length = struct.unpack_from("<III", frame, 1)
                        encoding, payload = frame[13:13 + length].decode(), json.loads(frame[13 + length:])
                        seen[f"call {call}"] = (service, encoding, payload)
                    continue
                doc = json.loads(frame)
                if doc["op"] == "parameterValues":
                    seen[f"parameters {doc.get('id')}"] = {p["name"]: p.get("value") for p in doc["parameters"]}
                elif doc["op"] == "status":
                    seen["status"].append(doc)
                else:
                    seen[doc["op"]] = doc
            return seen.get(key)

        info = await until("serverInfo")
        services = {s["name"]: s for s in (await until("advertiseServices"))["services"]}
        await ws.send(json.dumps({"op": "getParameters", "parameterNames": ["window", "method", "partition"],
                                  "id": "get"}))
        await until("parameters get")
        await ws.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "all"}))
        await until("parameters all")
        await ws.send(json.dumps({"op": "setParameters", "parameters": [{"name": "solve_rate", "value": 3.5}],
                                  "id": "accepted"}))
        await until("parameters accepted")
        await ws.send(json.dumps({"op": "setParameters", "parameters": [{"name": "window", "value": 100}],
                                  "id": "refused"}))
        await until("parameters refused", lambda: "parameters refused" in seen and seen["status"])
        solve = services["/hammer_ros/solve"]
        encoding = b"json"
        await ws.send(struct.pack("<BIII", 2, solve["id"], 7, len(encoding)) + encoding + b"{}")
        await until("call 7")
        return {"info": info, "services": services, **seen}


def test_parameters_and_services_over_the_websocket(rig):
    seen = asyncio.run(asyncio.wait_for(_parameters_and_services(rig.port), 120))
    assert {"parameters", "services"} <= set(seen["info"]["capabilities"])
    assert set(seen["services"]) == {f"/hammer_ros/{name}" for name in ("reset", "solve", "diagnose")}
    assert seen["services"]["/hammer_ros/solve"]["type"] == "std_srvs/srv/Trigger"
    assert seen["parameters get"] == {"window": NODE["window"], "method": "cls-markov"}  # partition: unset
    everything = seen["parameters all"]
    assert set(everything) == set(PARAMETERS) - {"partition"}  # every parameter with a value
    assert everything["foxglove_port"] == rig.port and everything["order"] == NODE["order"]
    assert seen["parameters accepted"] == {"solve_rate": 3.5}
    assert seen["parameters refused"] == {"window": NODE["window"]}  # unchanged, and the ROS reason says why
    refusal = "window: must be >= max(16, 2 tau_max + 2) = 122 samples (got 100)"  # as from ros2 param set
    assert [s["message"] for s in seen["status"]] == [refusal]
    service, encoding, response = seen["call 7"]
    assert (service, encoding) == (seen["services"]["/hammer_ros/solve"]["id"], "json")
    assert response["success"] is True and json.loads(response["message"])["order"] == NODE["order"]


def test_foxglove_ws_protocol_clients(rig):
    """The same with two clients of Foxglove's own library (@foxglove/ws-protocol 0.8.0): no
    duplicate for the watcher while the other resubscribes 30 times, parameters and ~/solve; its
    default subprotocol alone (foxglove.websocket.v1) is refused by the SDK's handshake."""
    code, seen = run_checker("ws_clients.mjs", str(rig.port))
    assert code == 0, seen
    assert seen["legacy_status"] == 400
    assert {"parameters", "services"} <= set(seen["capabilities"])
    assert seen["services"] == [f"/hammer_ros/{name}" for name in ("diagnose", "reset", "solve")]
    assert seen["cycles_with_model"] == 30
    assert seen["watcher_duplicates"] == dict.fromkeys(seen["watcher_duplicates"], 0)  # on every channel
    assert seen["watcher_messages"][dashboard_topic("model")] >= 2
    assert seen["parameters"]["get"]["window"] == NODE["window"] and seen["parameters"]["get"]["method"] == "cls-markov"
    assert seen["parameters"]["accepted"] == {"solve_rate": 3.0}
    assert seen["parameters"]["refused"] == {"window": NODE["window"]}
    assert seen["statuses"] == ["window: must be >= max(16, 2 tau_max + 2) = 122 samples (got 100)"]
    assert seen["solve"]["encoding"] == "json" and seen["solve"]["payload"]["success"] is True


def test_a_parameter_set_from_ros_reaches_the_subscribed_foxglove_clients(rig):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    client = FoxgloveClient(rig.port, (), first_frames=(
        {"op": "subscribeParameterUpdates", "parameterNames": ["solve_rate"]},
        {"op": "getParameters", "parameterNames": ["solve_rate"], "id": "subscribed"}))  # answered after it
    try:
        rig.wait_for(lambda: client.error or any(p.get("id") == "subscribed" for p in client.parameter_values),
                     what="the parameter subscription")
        ros = AsyncParameterClient(rig.node, "hammer_ros")
        rig.wait_for(ros.services_are_ready, what="the node's parameter services")
        [result] = rig.wait_future(ros.set_parameters([Parameter("solve_rate", value=4.25)])).results
        assert result.successful
        update = rig.wait_for(lambda: [p for p in client.parameter_values if "id" not in p],
                              what="the change on the Foxglove client")
        assert update[-1]["parameters"] == [{"name": "solve_rate", "value": 4.25, "type": "float64"}]
    finally:
        client.close()


def test_the_server_listens_on_loopback_only(rig):
    assert listening_sockets(rig.process.process.pid) == [("127.0.0.1", rig.port)]


def test_misbehaving_clients_never_take_the_node_down(rig):
    asyncio.run(asyncio.wait_for(_misbehave(rig.port), 120))

    def counted():
        d = rig.diagnostics[-1] if rig.diagnostics else {}
        return (int(d.get("foxglove_invalid_frames", 0)) >= 3 and int(d.get("foxglove_client_errors", 0)) >= 1
                and int(d.get("foxglove_subscribe_requests", 0)) >= FLOOD
                and int(d.get("foxglove_disconnections", 0)) >= 2 and d)

    rig.wait_for(counted, what="the misbehaviour counted in /diagnostics")
    # every client gone: the last one's subscriptions may be dropped a /diagnostics after its disconnection is counted
    rig.wait_for(lambda: counted() and int(counted()["foxglove_subscriptions"]) == 0,
                 what="no Foxglove subscription left after the misbehaving clients")
    assert rig.process.process.poll() is None
    seen = len(rig.models)
    rig.wait_for(lambda: len(rig.models) > seen, what="models after the misbehaving clients")
    client = FoxgloveClient(rig.port, (dashboard_topic("model"),))  # and it still serves
    try:
        rig.wait_for(lambda: client.error or client.messages[dashboard_topic("model")], what="a model for a new client")
        assert client.error is None
    finally:
        client.close()


def test_with_foxglove_port_0_nothing_listens(tmp_path):
    with DomainLease() as lease:
        env = child_environment(lease.domain_id, log_dir=tmp_path / "ros_log")
        node = RosProcess("hammer_ros.ros.node", {"diagnosis_period": 0.0}, env, tmp_path / "node.log")
        listener = Listener(env)
        try:
            diagnostics = listener.subscribe_diagnostics()
            listener.wait_for(lambda: diagnostics, what="the node's diagnostics")  # configured and solving
            assert "foxglove_port" not in diagnostics[-1]
            assert listening_sockets(node.process.pid) == []
        finally:
            listener.close()
            code = node.stop(signal.SIGINT)
        assert code == 0, node.output()[-3000:]
