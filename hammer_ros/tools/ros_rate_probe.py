"""How many messages per second reach a subscriber without loss: the hammer_ros node vs a bare
rclpy subscriber (EventsExecutor running its own loop, as the node), on a private ROS_DOMAIN_ID on loopback.

    python -m hammer_ros.tools.ros_rate_probe [--rates 1000,5000,10000] [--batch 1] [--seconds 4]

For each rate R a publisher process sends R messages/s on each of /command and /response
(std_msgs/Float64, or Float64MultiArray of ``--batch`` samples; reliable, depth 1000) for
``--seconds`` seconds, once to a bare subscriber (this process, with the node's QoS: best
effort, the node's default ``qos_depth``) and once to a fresh
``hammer-ros node`` (whose /diagnostics counters are read back). The publisher starts once both
ends have matched (the bare subscriber's matched-publisher counts, the node's
``*_publishers`` on /diagnostics), not after a fixed wait. A rate is sustained when every
published sample was received. Each run also reports the CPU seconds the subscriber's process (all
its threads, from the go until every sample was counted) and the publisher (while publishing) spent:
``subscriber_cpu_seconds``, ``publisher_cpu_seconds``. Output: one JSON document per line on stdout. Reusable by
``hammer-ros bench`` through :func:`probe`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import select
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np

from ..ros.environment import DomainLease, child_environment, prepare_ros_environment
from .process_status import child_pids, process_cpu_seconds, process_status_kib

TOPICS = ("/command", "/response")
JOINT_TOPIC = "/joint_states"  # ``--joints N``: one JointState of N named joints (position u, velocity y)
MATCH_TIMEOUT = 15.0
PUBLISHER_MATCH_TIMEOUT = 2 * MATCH_TIMEOUT  # the publisher starts beside a node that starts up (``_node``)
SETTLE_SECONDS = 1.0
# A subscriber that lost samples never counts them all: the wait for the rest ends once nothing has come
# for QUIET_SECONDS (bare), or over QUIET_UPDATES /diagnostics of the node (4 a second) in a row.
QUIET_SECONDS = 0.3
QUIET_UPDATES = 3
MAX_LAG = 0.02  # s behind its schedule at which the publisher counts a stall and resumes without a burst


PLANT_MESSAGES = 64  # distinct (u, y) message pairs cycled by a --plant publisher


def _plant_messages(batch: int) -> list[tuple]:
    """(u, y) Float64MultiArray pairs of paper 000's G1 with tanh(8v)/8, one continuous record."""
    from std_msgs.msg import Float64MultiArray

    from ..identification.simulate import HammersteinStream
    from .reproduce.cls import G1, INPUT_STD, NONLINEARITIES

    plant = HammersteinStream(NONLINEARITIES["F2"][1], G1)
    rng = np.random.default_rng(5)
    pairs = []
    for _ in range(PLANT_MESSAGES):
        v = INPUT_STD * rng.standard_normal(batch)
        pairs.append(tuple(Float64MultiArray(data=x.tolist()) for x in (v, plant(v))))
    return pairs


class Schedule:
    """The publisher's message slots: message k is due at start + k / rate. ``due(now)`` is how many
    messages should have gone out by ``now`` (at most ``total``); when the next one is more than
    MAX_LAG late (the publisher was descheduled), the schedule restarts at ``now`` instead, so the
    messages missed are never sent in one burst, and the stall is counted (``stalls``, its time in
    ``stalled``)."""

    def __init__(self, rate: float, total: int, now: float) -> None:
        self.rate, self.total = rate, total
        self.began = self.start = now
        self.sent, self.stalled, self.stalls = 0, 0.0, 0

    def slot(self, k: int) -> float:
        return self.start + k / self.rate

    def due(self, now: float) -> int:
        behind = now - self.slot(self.sent)
        if behind > MAX_LAG:
            self.start += behind
            self.stalled += behind
            self.stalls += 1
        return min(self.total, int((now - self.start) * self.rate) + 1)

    def run(self, send: Callable[[int], None], clock: Callable[[], float] = time.monotonic,
            sleep: Callable[[float], None] = time.sleep) -> None:
        """``send(k)`` each message k < total in its slot. Until all are sent: after a restart the
        next slot is now, and a rounding that makes none due yet only sleeps (0 s) again."""
        while self.sent < self.total:
            due = self.due(clock())
            for k in range(self.sent, due):
                send(k)
            self.sent = max(self.sent, due)
            sleep(max(0.0, self.slot(self.sent) - clock()))


def _joint_state(joints: int):
    """The JointState of the ``--joints`` runs: joints joint_0.. with positions and velocities."""
    from sensor_msgs.msg import JointState

    values = [float(i) / joints for i in range(joints)]
    return JointState(name=[f"joint_{i}" for i in range(joints)], position=values, velocity=values)


def _publish(rate: float, seconds: float, batch: int, plant: bool = False, joints: int = 0) -> int:
    """Publisher process: wait for a subscriber on both topics, say so (a line on stdout), wait for
    the go (a line on stdin: ``_start_when_subscribed``), publish on a ``Schedule``, print the count
    sent and the stalls. The same message every time, or (``plant``) a Hammerstein record cycled.
    Without the schedule's restart, a 0.3 s stall at 7000/s was a catch-up burst of about 2000
    messages per topic, more than a subscriber's history holds: a loss of the publisher's making."""
    import rclpy
    from std_msgs.msg import Float64, Float64MultiArray

    rclpy.init()
    node = rclpy.create_node("rate_probe_publisher")
    msg_type = Float64 if batch == 1 else Float64MultiArray
    pubs = ([node.create_publisher(type(_joint_state(joints)), JOINT_TOPIC, 1000)] if joints else
            [node.create_publisher(msg_type, topic, 1000) for topic in TOPICS])
    deadline = time.monotonic() + PUBLISHER_MATCH_TIMEOUT
    while any(p.get_subscription_count() == 0 for p in pubs) and time.monotonic() < deadline:
        time.sleep(0.01)
    print(json.dumps({"matched": True}), flush=True)
    sys.stdin.readline()  # the subscriber has matched both writers too
    values = [float(i % 97) / 97.0 for i in range(batch)]
    message = Float64(data=0.5) if batch == 1 else Float64MultiArray(data=values)
    pairs = _plant_messages(batch) if plant else [(_joint_state(joints),)] if joints else [(message, message)]
    def send(k: int) -> None:
        for pub, msg in zip(pubs, pairs[k % len(pairs)]):
            pub.publish(msg)

    schedule = Schedule(rate, int(rate * seconds), time.monotonic())
    cpu = time.process_time()
    schedule.run(send)
    elapsed, cpu = time.monotonic() - schedule.began, time.process_time() - cpu
    print(json.dumps({"messages": schedule.sent, "publish_seconds": elapsed, "stalled_seconds": schedule.stalled,
                      "stalls": schedule.stalls, "publisher_cpu_seconds": cpu}), flush=True)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _start_publisher(env: dict, rate: float, seconds: float, batch: int, plant: bool = False,
                     joints: int = 0) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "hammer_ros.tools.ros_rate_probe", "--publish", "--rates", str(rate),
           "--seconds", str(seconds), "--batch", str(batch), *(["--plant"] if plant else []),
           *(["--joints", str(joints)] if joints else [])]
    return subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def _start_when_subscribed(publisher: subprocess.Popen, executor, subscribed: Callable[[], bool]) -> None:
    """Let ``publisher`` start once both ends are matched: it has matched the subscriber's readers
    when it says so (its first line), the subscriber has matched its writers when ``subscribed()``
    (the subscriber's own discovery, which can lag on a loaded machine; the middleware drops a
    message sent to a reader that has not matched the writer yet, which would count as lost)."""
    if not publisher.stdout.readline():  # exited without matching: ``_result`` reports it
        return
    _spin_until(executor, subscribed, MATCH_TIMEOUT)
    publisher.stdin.write("go\n")
    publisher.stdin.flush()


def _result_ready(publisher: subprocess.Popen) -> bool:
    """The publisher printed its count (or exited): ``_result`` will not block."""
    return bool(select.select([publisher.stdout], [], [], 0)[0]) or publisher.poll() is not None


def _result(publisher: subprocess.Popen) -> dict:
    """The publisher's count line. It then lingers 0.5 s (the last messages leave) while the
    subscriber counts what is still on its way; ``_reap`` waits for its exit afterwards."""
    line = publisher.stdout.readline()
    if not line:
        raise RuntimeError(f"the rate probe's publisher exited {publisher.wait(timeout=30)} without a count")
    return json.loads(line)


def _reap(publisher: subprocess.Popen) -> None:
    publisher.communicate(timeout=120)


def _finish(publisher: subprocess.Popen) -> dict:
    """The count line, once the publisher has exited."""
    sent = _result(publisher)
    _reap(publisher)
    return sent


def _bare(node, executor, env: dict, rate: float, seconds: float, batch: int) -> dict:
    """Count messages in this process (EventsExecutor running its own loop, as the node)."""
    from std_msgs.msg import Float64, Float64MultiArray

    counts = {topic: 0 for topic in TOPICS}
    msg_type = Float64 if batch == 1 else Float64MultiArray
    from rclpy.qos import QoSProfile, qos_profile_sensor_data
    from rclpy.task import Future

    from ..ros.node_core import PARAMETERS

    qos = QoSProfile(depth=PARAMETERS["qos_depth"].default, reliability=qos_profile_sensor_data.reliability,
                     durability=qos_profile_sensor_data.durability)  # what the node subscribes with
    subs = [node.create_subscription(msg_type, topic, lambda m, t=topic: counts.__setitem__(t, counts[t] + 1), qos)
            for topic in TOPICS]
    never = Future()  # spin_until_future_complete on it: the executor's own event loop, as the node runs it
    publisher = _start_publisher(env, rate, seconds, batch)
    _start_when_subscribed(publisher, executor, lambda: all(sub.get_publisher_count() for sub in subs))
    cpu = time.process_time()
    while not _result_ready(publisher):
        executor.spin_until_future_complete(never, timeout_sec=0.05)
    sent = _result(publisher)
    settle = time.monotonic() + SETTLE_SECONDS  # what is still on its way, until every message is counted
    total, moved = sum(counts.values()), time.monotonic()
    while (min(counts.values()) < sent["messages"] and (now := time.monotonic()) < settle
           and now - moved < QUIET_SECONDS):
        executor.spin_until_future_complete(never, timeout_sec=0.05)
        if sum(counts.values()) != total:
            total, moved = sum(counts.values()), time.monotonic()
    cpu = time.process_time() - cpu  # over the same span as the node's: from the go until all was counted
    _reap(publisher)
    for sub in subs:
        node.destroy_subscription(sub)
    return {"subscriber": "bare rclpy (EventsExecutor)", "received": min(counts.values()) * batch, **sent,
            "subscriber_cpu_seconds": cpu}


class _Updates(list):
    """The node's received-sample count (the lower of its two inputs') at each /diagnostics."""

    def settled(self, since: int) -> bool:
        """The last QUIET_UPDATES counts after the first ``since`` are the same: nothing more arrives."""
        last = self[since:][-QUIET_UPDATES:]
        return len(last) == QUIET_UPDATES and len(set(last)) == 1


def _diagnostics_counters(node):
    """Subscribe to /diagnostics: the hammer_ros status's key/value pairs, updated in place, and
    the received count at each message (``_Updates``)."""
    from diagnostic_msgs.msg import DiagnosticArray

    latest: dict[str, str] = {}
    updates = _Updates()

    def on_diagnostics(msg) -> None:
        for status in msg.status:
            if status.name.startswith("hammer_ros"):
                latest.update({kv.key: kv.value for kv in status.values})
                updates.append(min(int(latest.get(k, 0)) for k in ("received_excitation", "received_response")))

    return latest, updates, node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)


def _node_subscribed(latest: dict[str, str]) -> bool:
    """The node's latest /diagnostics has a matched publisher on both inputs."""
    return all(int(latest.get(f"{stream}_publishers", 0)) > 0 for stream in ("excitation", "response"))


def _start_node(env: dict, params: list[str], batch: int) -> subprocess.Popen:
    """A fresh ``hammer-ros node`` on TOPICS (Float64 or Float64MultiArray ``data[:]``)."""
    field = "data" if batch == 1 else "data[:]"
    type_name = "std_msgs/msg/Float64" if batch == 1 else "std_msgs/msg/Float64MultiArray"
    for stream, topic in zip(("excitation", "response"), TOPICS):
        params = [*params, f"{stream}_topic:={topic}", f"{stream}_type:={type_name}", f"{stream}_field:={field}"]
    cmd = [sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", *[a for p in params for a in ("-p", p)]]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _spin_until(executor, done, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return done()


class _FoxgloveClient:
    """A Foxglove WebSocket client (``websockets``) in a thread, subscribed to every channel of
    the node's server, counting the messages it receives."""

    def __init__(self, port: int) -> None:
        import asyncio
        import threading

        self.port, self.messages, self._stop = port, 0, threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self._thread.start()

    async def _run(self) -> None:
        """Connect (retrying while the node's server is not listening yet), subscribe to every
        advertised channel and count the messages until ``close``."""
        import asyncio

        import websockets

        while not self._stop.is_set():
            try:
                await self._receive(websockets.connect(f"ws://127.0.0.1:{self.port}",
                                                       subprotocols=["foxglove.sdk.v1"]))
                return
            except OSError:  # refused: the server is not up yet
                await asyncio.sleep(0.1)

    async def _receive(self, connection) -> None:
        import asyncio

        async with connection as ws:
            while not self._stop.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.1)
                except asyncio.TimeoutError:
                    continue
                if isinstance(frame, bytes):
                    self.messages += 1
                elif (doc := json.loads(frame))["op"] == "advertise":
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": c["id"], "channelId": c["id"]} for c in doc["channels"]]}))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _node(node, executor, env: dict, rate: float, seconds: float, batch: int, foxglove: bool = False) -> dict:
    """Run a fresh hammer_ros node and read its received-sample counters from /diagnostics; with
    ``foxglove`` its Foxglove server on and one client subscribed to every channel."""
    latest, updates, sub = _diagnostics_counters(node)
    port = _free_port() if foxglove else 0
    ident = _start_node(env, [f"sample_rate:={rate * batch}", "solve_rate:=4.0", "window:=4000",
                              f"foxglove_port:={port}"], batch)
    publisher = _start_publisher(env, rate, seconds, batch)  # its start-up beside the node's; it waits for the go
    client, sent = None, None
    try:
        _spin_until(executor, lambda: bool(latest) or ident.poll() is not None, MATCH_TIMEOUT)  # up: diagnostics
        if ident.poll() is not None:  # refused its parameters (or crashed): not a measurement
            reason = (ident.stderr.read().strip().splitlines() or ["no output"])[-1]
            return {"subscriber": "hammer_ros node" + (" + foxglove client" if foxglove else ""), "received": 0,
                    "messages": 0, "publish_seconds": 0.0, "error": f"node exited {ident.returncode}: {reason}"}
        if foxglove:
            client = _FoxgloveClient(port)
            _spin_until(executor, lambda: client.messages > 0, MATCH_TIMEOUT)  # connected and receiving
        _start_when_subscribed(publisher, executor, lambda: _node_subscribed(latest))
        cpu = process_cpu_seconds(ident.pid)
        _spin_until(executor, lambda: _result_ready(publisher), 120)
        sent = _result(publisher)
        expected, since = sent["messages"] * batch, len(updates)
        _spin_until(executor, lambda: min(int(latest.get(k, 0)) for k in (
            "received_excitation", "received_response")) >= expected or updates.settled(since), SETTLE_SECONDS + 1.0)
        end = process_cpu_seconds(ident.pid)
        sent["subscriber_cpu_seconds"] = None if cpu is None or end is None else end - cpu
    finally:
        if client is not None:
            client.close()
        if sent is None:  # the node never came up: the publisher still waits for it, or for the go
            publisher.kill()
        ident.terminate()
        _reap(publisher)
        try:
            ident.communicate(timeout=10)
        except subprocess.TimeoutExpired:  # still finishing its backlog: not part of the measurement
            ident.kill()
            ident.communicate()
        node.destroy_subscription(sub)
    received = min(int(latest.get(k, 0)) for k in ("received_excitation", "received_response"))
    return {"subscriber": "hammer_ros node" + (" + foxglove client" if foxglove else ""), "received": received,
            "aligned": int(latest.get("aligned", 0)), **sent,
            **({"foxglove_messages": client.messages} if client is not None else {})}


def node_memory(window: int, batch: int = 1000, rate: float = 200.0) -> dict:
    """Resident memory of a fresh ``hammer-ros node`` (window W, cls-markov, 1 solve/s, a
    diagnosis every 2 s) idle after startup, and its peak (VmHWM) once a Hammerstein record
    (``batch`` samples per message, ``rate`` messages/s per topic) has filled the window and
    the node has solved on it at least twice and diagnosed its newest ``diagnosis_window``."""
    prepare_ros_environment()
    with DomainLease() as lease:
        env = child_environment(lease.domain_id)
        os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTRTPS_DEFAULT_PROFILES_FILE")})
        import rclpy
        from rclpy.experimental import EventsExecutor
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import String

        from ..ros.node import PARAMETERS

        context = rclpy.Context()  # its own context and no signal handlers: callable from any process
        rclpy.init(context=context, domain_id=lease.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("memory_probe", context=context)
        executor = EventsExecutor(context=context)
        executor.add_node(node)
        latest, _, _ = _diagnostics_counters(node)
        diagnoses: list[int] = []
        node.create_subscription(String, "/hammer_ros/diagnosis",
                                 lambda m: diagnoses.append(json.loads(m.data).get("samples", 0)), 10)
        params = [f"sample_rate:={rate * batch}", f"window:={window}", "solve_rate:=1.0", "diagnosis_period:=2.0",
                  "max_gap:=1.0"]
        ident = _start_node(env, params, batch)
        try:
            if not _spin_until(executor, lambda: bool(latest), MATCH_TIMEOUT):
                raise RuntimeError("the node published no diagnostics")
            idle = process_status_kib("VmRSS", ident.pid)
            seconds = 1.2 * window / (rate * batch) + 1.0
            publisher = _start_publisher(env, rate, seconds, batch, plant=True)
            _start_when_subscribed(publisher, executor, lambda: _node_subscribed(latest))
            full = lambda: int(latest.get("window_samples", 0)) >= window  # noqa: E731
            _spin_until(executor, lambda: full() or publisher.poll() is not None, seconds + MATCH_TIMEOUT)
            def attempts() -> int:
                return int(latest.get("solves", 0)) + int(latest.get("solve_errors", 0))

            diagnosed = min(window, PARAMETERS["diagnosis_window"].default)
            solves = attempts()
            done = _spin_until(executor, lambda: attempts() >= solves + 2 and max(diagnoses, default=0) >= diagnosed,
                               120)
            peak = process_status_kib("VmHWM", ident.pid)
            workers = 0
            for child in child_pids(ident.pid):  # its solver and diagnosis processes (and multiprocessing's tracker)
                try:
                    workers += process_status_kib("VmHWM", child)
                except (RuntimeError, OSError):  # gone meanwhile
                    continue
            _finish(publisher)
        finally:
            ident.terminate()
            ident.communicate(timeout=30)
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=context)
    return {"window": window, "idle_kib": idle, "peak_kib": peak, "workers_peak_kib": workers, "filled": full(),
            "solved": done,
            "window_samples": int(latest.get("window_samples", 0)),
            "diagnosis_samples": diagnoses[-1] if diagnoses else 0}


def joint_state_params(path, joints: int, rate: float) -> None:
    """A node params file of ``joints`` channels joint_0.. over JOINT_TOPIC (u = position[joint_k],
    y = velocity[joint_k])."""
    lines = ["hammer_ros:", "  ros__parameters:", f"    excitation_topic: {JOINT_TOPIC}",
             "    excitation_type: sensor_msgs/msg/JointState", f"    response_topic: {JOINT_TOPIC}",
             "    response_type: sensor_msgs/msg/JointState", f"    sample_rate: {float(rate)}", "    solve_rate: 4.0",
             "    window: 4000", f"    channels: [{', '.join(f'joint_{k}' for k in range(joints))}]"]
    lines += [f'    joint_{k}: {{excitation_field: "position[joint_{k}]", response_field: "velocity[joint_{k}]"}}'
              for k in range(joints)]
    path.write_text("\n".join(lines) + "\n")


def _joints_bare(session: ProbeSession, rate: float, seconds: float, joints: int) -> dict:
    """The bare subscriber of the JointState topic of ``joints`` joints: the probe's row (``_bare``)."""
    from rclpy.qos import QoSProfile, qos_profile_sensor_data
    from rclpy.task import Future

    from ..ros.node_core import PARAMETERS

    node, executor = session.node, session.executor
    never = Future()
    count = [0]
    qos = QoSProfile(depth=PARAMETERS["qos_depth"].default, reliability=qos_profile_sensor_data.reliability,
                     durability=qos_profile_sensor_data.durability)
    sub = node.create_subscription(type(_joint_state(joints)), JOINT_TOPIC,
                                   lambda m: count.__setitem__(0, count[0] + 1), qos)
    publisher = _start_publisher(session.env, rate, seconds, 1, joints=joints)
    _start_when_subscribed(publisher, executor, lambda: sub.get_publisher_count() > 0)
    cpu = time.process_time()
    while not _result_ready(publisher):
        executor.spin_until_future_complete(never, timeout_sec=0.05)
    sent = _result(publisher)
    _spin_until(executor, lambda: count[0] >= sent["messages"], SETTLE_SECONDS)
    cpu = time.process_time() - cpu
    _reap(publisher)
    node.destroy_subscription(sub)
    return {"subscriber": "bare rclpy (EventsExecutor)", "received": count[0], **sent, "subscriber_cpu_seconds": cpu}


def _joints_node(session: ProbeSession, rate: float, seconds: float, joints: int) -> dict:
    """A fresh node of ``joints`` channels over the JointState topic (``joint_state_params``): the
    probe's row, ``received`` the smallest count of any channel's inputs (/diagnostics, one status
    per channel), with the largest DDS-lost and queue-dropped counts and the node's CPU."""
    import tempfile
    from pathlib import Path

    from diagnostic_msgs.msg import DiagnosticArray

    node, executor, env = session.node, session.executor, session.env
    statuses: dict[str, dict[str, str]] = {}

    def on_diagnostics(msg) -> None:
        for status in msg.status:
            statuses[status.name] = {kv.key: kv.value for kv in status.values}

    diagnostics = node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)

    def received() -> int:
        keys = ("received_excitation", "received_response")
        return min((int(v.get(k, 0)) for v in statuses.values() for k in keys), default=0)

    with tempfile.TemporaryDirectory() as tmp:
        params = Path(tmp) / "joints.yaml"
        joint_state_params(params, joints, rate)
        ident = subprocess.Popen([sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "--params-file",
                                  str(params)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        publisher = _start_publisher(env, rate, seconds, 1, joints=joints)
        try:
            _spin_until(executor, lambda: len(statuses) == joints and all(
                int(v.get("excitation_publishers", 0)) for v in statuses.values()), 2 * MATCH_TIMEOUT)
            _start_when_subscribed(publisher, executor, lambda: True)
            cpu = process_cpu_seconds(ident.pid)
            _spin_until(executor, lambda: _result_ready(publisher), 120)
            sent = _result(publisher)
            _spin_until(executor, lambda: received() >= sent["messages"], SETTLE_SECONDS + 1.0)
            end = process_cpu_seconds(ident.pid)
            sent["subscriber_cpu_seconds"] = None if cpu is None or end is None else end - cpu
        finally:
            _reap(publisher)
            ident.terminate()
            ident.communicate(timeout=20)
            node.destroy_subscription(diagnostics)
    return {"subscriber": "hammer_ros node", "received": received(), **sent,
            **{f"node_{what}": max((int(v.get(f"response_{what}", 0)) for v in statuses.values()), default=0)
               for what in ("dds_lost", "queue_dropped")}}


SUBSCRIBERS = ("bare", "node", "foxglove")


class ProbeSession:
    """A private ROS_DOMAIN_ID, an rclpy context and the counting node shared by many probe runs
    (``probe``): their set-up, about 0.75 s on the 2-core bench VM, once rather than per rate."""

    def __enter__(self) -> ProbeSession:
        prepare_ros_environment()
        self._stack = contextlib.ExitStack()
        lease = self._stack.enter_context(DomainLease())
        self.env = child_environment(lease.domain_id)
        os.environ.update({k: self.env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                                    "FASTRTPS_DEFAULT_PROFILES_FILE")})
        import rclpy
        from rclpy.experimental import EventsExecutor

        rclpy.init()
        self.node = rclpy.create_node("rate_probe")
        self.executor = EventsExecutor()
        self.executor.add_node(self.node)
        return self

    def __exit__(self, *exc) -> None:
        import rclpy

        try:
            self.node.destroy_node()
            rclpy.try_shutdown()
        finally:
            self._stack.close()

    def probe(self, rates: list[float], batch: int = 1, seconds: float = 4.0, foxglove: bool = False,
              subscribers: tuple[str, ...] = ("bare", "node")) -> list[dict]:
        """Rows {subscriber, rate_msgs_per_s, batch, messages, received, lost, ...} for each rate
        and each of ``subscribers`` (SUBSCRIBERS: the bare subscriber, the node, the node with its
        Foxglove server on and one client connected); ``foxglove`` adds the last."""
        chosen = set(subscribers) | ({"foxglove"} if foxglove else set())
        rows = []
        for rate in rates:
            runs = {"bare": (_bare, {}), "node": (_node, {}), "foxglove": (_node, {"foxglove": True})}
            for measure, options in (runs[who] for who in SUBSCRIBERS if who in chosen):
                row = measure(self.node, self.executor, self.env, rate, seconds, batch, **options)
                row.update(rate_msgs_per_s=rate, batch=batch, samples_per_s=rate * batch,
                           lost=row["messages"] * batch - row["received"])
                rows.append(row)
                print(json.dumps(row), flush=True)
        return rows

    def joints_probe(self, rates: list[float], batch: int = 1, seconds: float = 4.0,
                     subscribers: tuple[str, ...] = ("bare", "node"), joints: int = 6) -> list[dict]:
        """``probe``'s rows for one JointState topic of ``joints`` named joints (one message =
        one sample per joint), read by the bare subscriber and by one node of ``joints`` channels
        (``_joints_node``); ``batch`` must be 1."""
        if batch != 1:
            raise ValueError(f"joints_probe: batch {batch}: a JointState carries one sample per joint")
        runs = {"bare": _joints_bare, "node": _joints_node}
        rows = []
        for rate in rates:
            for who in (w for w in ("bare", "node") if w in subscribers):
                row = runs[who](self, rate, seconds, joints)
                row.update(rate_msgs_per_s=rate, batch=1, joints=joints, samples_per_s=rate,
                           lost=row["messages"] - row["received"])
                rows.append(row)
                print(json.dumps(row), flush=True)
        return rows


def probe(rates: list[float], batch: int = 1, seconds: float = 4.0, foxglove: bool = False,
          subscribers: tuple[str, ...] = ("bare", "node")) -> list[dict]:
    """``ProbeSession.probe`` in a session of its own."""
    with ProbeSession() as session:
        return session.probe(rates, batch, seconds, foxglove, subscribers)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hammer_ros.tools.ros_rate_probe",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--rates", default="1000,2000,5000,10000", help="messages/s per topic, comma-separated")
    parser.add_argument("--batch", type=int, default=1, help="samples per message (1 = Float64)")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--foxglove", action="store_true", help="also the node with its Foxglove server and a client")
    parser.add_argument("--publish", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--plant", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--joints", type=int, default=0,
                        help="one JointState topic of N joints read by N channels of one node (vs a bare subscriber)")
    args = parser.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    if args.publish:
        prepare_ros_environment()
        return _publish(rates[0], args.seconds, args.batch, args.plant, args.joints)
    if args.joints:
        with ProbeSession() as session:
            session.joints_probe(rates, seconds=args.seconds, joints=args.joints)
        return 0
    probe(rates, args.batch, args.seconds, args.foxglove)
    return 0


if __name__ == "__main__":
    sys.exit(main())
