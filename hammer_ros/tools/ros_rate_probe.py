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
from typing import Any

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
RESEND = 2.0  # s without a service response before the request is sent again (``_call``)
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


def _serve(batch: int, prefixes: list[str], plant: bool = False, joints: int = 0) -> int:
    """Publisher process of a probe session: publishers of every prefix's topics (``_topics``).
    For each command line on stdin ({"prefix", "rate", "seconds"}) it waits for a subscriber on
    that prefix's topics, says so ({"matched": bool}), waits for the go (a line:
    ``_Publisher.start``), publishes on a ``Schedule`` and prints the count sent and the stalls;
    it exits at the end of its input. The same message every time, or (``plant``) a Hammerstein
    record cycled. Without the schedule's restart, a 0.3 s stall at 7000/s was a catch-up burst of
    about 2000 messages per topic, more than a subscriber's history holds: a loss of the
    publisher's making."""
    import rclpy
    from std_msgs.msg import Float64, Float64MultiArray

    rclpy.init()
    node = rclpy.create_node("rate_probe_publisher")
    msg_type = type(_joint_state(joints)) if joints else Float64 if batch == 1 else Float64MultiArray
    pubs = {prefix: [node.create_publisher(msg_type, topic, 1000) for topic in _topics(prefix, joints)]
            for prefix in prefixes}
    values = [float(i % 97) / 97.0 for i in range(batch)]
    message = Float64(data=0.5) if batch == 1 else Float64MultiArray(data=values)
    pairs = _plant_messages(batch) if plant else [(_joint_state(joints),)] if joints else [(message, message)]
    while line := sys.stdin.readline():
        command = json.loads(line)
        targets = pubs[command["prefix"]]
        deadline = time.monotonic() + PUBLISHER_MATCH_TIMEOUT
        while any(p.get_subscription_count() == 0 for p in targets) and time.monotonic() < deadline:
            time.sleep(0.01)
        print(json.dumps({"matched": all(p.get_subscription_count() for p in targets)}), flush=True)
        sys.stdin.readline()  # the go: the subscriber has matched these writers too

        def send(k: int, targets=targets) -> None:
            for pub, msg in zip(targets, pairs[k % len(pairs)]):
                pub.publish(msg)

        schedule = Schedule(command["rate"], int(command["rate"] * command["seconds"]), time.monotonic())
        cpu = time.process_time()
        schedule.run(send)
        elapsed, cpu = time.monotonic() - schedule.began, time.process_time() - cpu
        print(json.dumps({"messages": schedule.sent, "publish_seconds": elapsed, "stalled_seconds": schedule.stalled,
                          "stalls": schedule.stalls, "publisher_cpu_seconds": cpu}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _topics(prefix: str, joints: int = 0) -> list[str]:
    """The topics of one subscriber of a session: ``prefix`` + TOPICS, or + JOINT_TOPIC."""
    return [prefix + JOINT_TOPIC] if joints else [prefix + topic for topic in TOPICS]


class _Publisher:
    """The publisher process (``_serve``) of a probe session, started once for all its runs, with
    one pair of topics per subscriber (``prefixes``): only the subscriber of a run receives it,
    and no run pays for a process start and discovery."""

    def __init__(self, env: dict, batch: int, prefixes: list[str], plant: bool = False, joints: int = 0) -> None:
        cmd = [sys.executable, "-m", "hammer_ros.tools.ros_rate_probe", "--publish", "--batch", str(batch),
               "--prefixes", ",".join(prefixes), *(["--plant"] if plant else []),
               *(["--joints", str(joints)] if joints else [])]
        self.process = subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def _line(self) -> dict:
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"the rate probe's publisher exited {self.process.wait(timeout=30)}")
        return json.loads(line)

    def _say(self, text: str) -> None:
        self.process.stdin.write(text + "\n")
        self.process.stdin.flush()

    def start(self, executor, prefix: str, rate: float, seconds: float, subscribed: Callable[[], bool]) -> None:
        """A run of ``rate`` messages/s for ``seconds`` on ``prefix``'s topics, started once both
        ends are matched: the publisher has matched the subscriber's readers when it says so, the
        subscriber has matched its writers when ``subscribed()`` (the subscriber's own discovery,
        which can lag on a loaded machine; the middleware drops a message sent to a reader that has
        not matched the writer yet, which would count as lost)."""
        self._say(json.dumps({"prefix": prefix, "rate": rate, "seconds": seconds}))
        self._line()  # matched (or timed out: the run's count then shows it)
        _spin_until(executor, subscribed, MATCH_TIMEOUT)
        self._say("go")

    def ready(self) -> bool:
        """The publisher printed the run's count (or exited): ``result`` will not block."""
        return bool(select.select([self.process.stdout], [], [], 0)[0]) or self.process.poll() is not None

    def result(self) -> dict:
        """The run's count line; the process stays for the next run (the last messages leave meanwhile)."""
        return self._line()

    def close(self) -> None:
        """End its input: it exits after the run under way, if any."""
        self.process.stdin.close()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.process.stdout.close()


class _Updates(list):
    """The node's received-sample count (the lower of its two inputs') at each /diagnostics."""

    def settled(self, since: int) -> bool:
        """The last QUIET_UPDATES counts after the first ``since`` are the same: nothing more arrives."""
        last = self[since:][-QUIET_UPDATES:]
        return len(last) == QUIET_UPDATES and len(set(last)) == 1


def _diagnostics_counters(node, name: str = "hammer_ros"):
    """Subscribe to /diagnostics: the status of the node ``name`` (its key/value pairs, updated in
    place) and the received count at each of its messages (``_Updates``)."""
    from diagnostic_msgs.msg import DiagnosticArray

    latest: dict[str, str] = {}
    updates = _Updates()

    def on_diagnostics(msg) -> None:
        for status in msg.status:
            if status.hardware_id == name:
                latest.update({kv.key: kv.value for kv in status.values})
                updates.append(min(int(latest.get(k, 0)) for k in ("received_excitation", "received_response")))

    return latest, updates, node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)


def _node_subscribed(latest: dict[str, str]) -> bool:
    """The node's latest /diagnostics has a matched publisher on both inputs."""
    return all(int(latest.get(f"{stream}_publishers", 0)) > 0 for stream in ("excitation", "response"))


def _start_node(env: dict, params: list[str], batch: int, prefix: str = "", name: str = "hammer_ros",
                stderr=subprocess.PIPE) -> subprocess.Popen:
    """A fresh ``hammer-ros node`` called ``name`` on ``prefix`` + TOPICS (Float64 or
    Float64MultiArray ``data[:]``)."""
    field = "data" if batch == 1 else "data[:]"
    type_name = "std_msgs/msg/Float64" if batch == 1 else "std_msgs/msg/Float64MultiArray"
    for stream, topic in zip(("excitation", "response"), _topics(prefix)):
        params = [*params, f"{stream}_topic:={topic}", f"{stream}_type:={type_name}", f"{stream}_field:={field}"]
    cmd = [sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "-r", f"__node:={name}",
           *[a for p in params for a in ("-p", p)]]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=stderr, text=True)


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


def _call(executor, request: Callable[[], Any], what: str, timeout: float = 2 * MATCH_TIMEOUT):
    """The result of a service request (a callable making its future: idempotent), sent again
    every RESEND s without a response (Fast DDS drops a response whose reader it has not matched
    yet); RuntimeError after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        future = request()
        if _spin_until(executor, future.done, min(RESEND, deadline - time.monotonic())):
            return future.result()
    raise RuntimeError(f"no response to {what} in {timeout:g} s")


class _NodeProcess:
    """A ``hammer-ros node`` called ``name`` on ``prefix``'s topics (window 4000, cls-markov, 4
    solves/s; with ``foxglove`` its Foxglove server on and one client subscribed to every channel),
    kept for every run of a session. Before a run its sample rate is set (SetParameters) and its
    window reset (``~/reset``: the engine and its counters start at 0, as a fresh node's), after it
    reset again (so that it solves on an empty window while another subscriber's run goes on)."""

    def __init__(self, session: ProbeSession, name: str, prefix: str, batch: int, rate: float,
                 foxglove: bool = False) -> None:
        import tempfile

        from rclpy.parameter_client import AsyncParameterClient
        from std_srvs.srv import Trigger

        self.session, self.name, self.prefix, self.batch, self.rate = session, name, prefix, batch, rate
        self.latest, self.updates, self._sub = _diagnostics_counters(session.node, name)
        self._stderr = tempfile.TemporaryFile("w+")  # not a pipe: nobody reads it while the node runs
        port = _free_port() if foxglove else 0
        self.process = _start_node(session.env, [f"sample_rate:={rate * batch}", "solve_rate:=4.0", "window:=4000",
                                                 f"foxglove_port:={port}"], batch, prefix, name, self._stderr)
        self._parameters = AsyncParameterClient(session.node, name)
        self._reset = session.node.create_client(Trigger, f"/{name}/reset")
        self._trigger = Trigger.Request
        self.client = None
        _spin_until(session.executor, lambda: bool(self.latest) or self.process.poll() is not None,
                    MATCH_TIMEOUT)  # up: diagnostics
        if self.error() is None and foxglove:
            self.client = _FoxgloveClient(port)
            _spin_until(session.executor, lambda: self.client.messages > 0, MATCH_TIMEOUT)  # connected, receiving

    def error(self) -> str | None:
        """Why the node is not running (it refused its parameters or crashed), or None."""
        if self.process.poll() is None:
            return None if self.latest else "the node published no diagnostics"
        self._stderr.seek(0)
        reason = (self._stderr.read().strip().splitlines() or ["no output"])[-1]
        return f"node exited {self.process.returncode}: {reason}"

    def received(self) -> int:
        return min(int(self.latest.get(k, 0)) for k in ("received_excitation", "received_response"))

    def reset(self) -> None:
        _call(self.session.executor, lambda: self._reset.call_async(self._trigger()), f"/{self.name}/reset")

    def prepare(self, rate: float) -> str | None:
        """Set the sample rate of a run at ``rate`` messages/s and reset the window; why not, or None."""
        from rclpy.parameter import Parameter

        if rate != self.rate:
            [result] = _call(self.session.executor, lambda: self._parameters.set_parameters(
                [Parameter("sample_rate", value=float(rate * self.batch))]), f"/{self.name}/set_parameters").results
            if not result.successful:
                return f"sample_rate refused: {result.reason}"
            self.rate = rate
        self.reset()
        return None

    def run(self, rate: float, seconds: float) -> dict:
        """One run: the probe's row (received = the lower of its two inputs' counts on /diagnostics)."""
        executor, publisher = self.session.executor, self.session.publisher(self.batch)
        label = "hammer_ros node" + (" + foxglove client" if self.client is not None else "")
        why = self.error() or self.prepare(rate)
        if why:
            return {"subscriber": label, "received": 0, "messages": 0, "publish_seconds": 0.0, "error": why}
        shown = self.client.messages if self.client is not None else 0
        publisher.start(executor, self.prefix, rate, seconds, lambda: _node_subscribed(self.latest))
        cpu = process_cpu_seconds(self.process.pid)
        _spin_until(executor, publisher.ready, 120)
        sent = publisher.result()
        expected, since = sent["messages"] * self.batch, len(self.updates)
        _spin_until(executor, lambda: self.received() >= expected or self.updates.settled(since),
                    SETTLE_SECONDS + 1.0)
        end = process_cpu_seconds(self.process.pid)
        sent["subscriber_cpu_seconds"] = None if cpu is None or end is None else end - cpu
        row = {"subscriber": label, "received": self.received(), "aligned": int(self.latest.get("aligned", 0)),
               **sent, **({"foxglove_messages": self.client.messages - shown} if self.client is not None else {})}
        self.reset()
        return row

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        self.process.terminate()
        try:
            self.process.communicate(timeout=10)
        except subprocess.TimeoutExpired:  # still finishing a backlog: not part of any measurement
            self.process.kill()
            self.process.communicate()
        self._stderr.close()
        self.session.node.destroy_subscription(self._sub)
        self.session.node.destroy_client(self._reset)


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
        ident, publisher = _start_node(env, params, batch), None
        try:
            if not _spin_until(executor, lambda: bool(latest), MATCH_TIMEOUT):
                raise RuntimeError("the node published no diagnostics")
            idle = process_status_kib("VmRSS", ident.pid)
            seconds = 1.2 * window / (rate * batch) + 1.0
            publisher = _Publisher(env, batch, [""], plant=True)
            publisher.start(executor, "", rate, seconds, lambda: _node_subscribed(latest))
            full = lambda: int(latest.get("window_samples", 0)) >= window  # noqa: E731
            _spin_until(executor, lambda: full() or publisher.ready(), seconds + MATCH_TIMEOUT)
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
            publisher.result()
        finally:
            if publisher is not None:
                publisher.close()
            ident.terminate()
            ident.communicate(timeout=30)
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=context)
    return {"window": window, "idle_kib": idle, "peak_kib": peak, "workers_peak_kib": workers, "filled": full(),
            "solved": done,
            "window_samples": int(latest.get("window_samples", 0)),
            "diagnosis_samples": diagnoses[-1] if diagnoses else 0}


def joint_state_params(path, joints: int, rate: float, topic: str = JOINT_TOPIC) -> None:
    """A node params file of ``joints`` channels joint_0.. over ``topic`` (u = position[joint_k],
    y = velocity[joint_k])."""
    lines = ["hammer_ros:", "  ros__parameters:", f"    excitation_topic: {topic}",
             "    excitation_type: sensor_msgs/msg/JointState", f"    response_topic: {topic}",
             "    response_type: sensor_msgs/msg/JointState", f"    sample_rate: {float(rate)}", "    solve_rate: 4.0",
             "    window: 4000", f"    channels: [{', '.join(f'joint_{k}' for k in range(joints))}]"]
    lines += [f'    joint_{k}: {{excitation_field: "position[joint_{k}]", response_field: "velocity[joint_{k}]"}}'
              for k in range(joints)]
    path.write_text("\n".join(lines) + "\n")


def _subscriber_qos():
    """What the node subscribes with: best effort, its default ``qos_depth``."""
    from rclpy.qos import QoSProfile, qos_profile_sensor_data

    from ..ros.node_core import PARAMETERS

    return QoSProfile(depth=PARAMETERS["qos_depth"].default, reliability=qos_profile_sensor_data.reliability,
                      durability=qos_profile_sensor_data.durability)


class _BareSubscriber:
    """The bare rclpy subscriber of a session (this process, EventsExecutor running its own loop,
    as the node; the node's QoS), counting the messages of each of ``prefix``'s topics; kept for
    every run (idle while another subscriber's run goes on: nothing is published on its topics)."""

    def __init__(self, session: ProbeSession, prefix: str, batch: int, joints: int = 0) -> None:
        from std_msgs.msg import Float64, Float64MultiArray

        self.session, self.prefix, self.batch, self.joints = session, prefix, batch, joints
        msg_type = type(_joint_state(joints)) if joints else Float64 if batch == 1 else Float64MultiArray
        self.counts = dict.fromkeys(_topics(prefix, joints), 0)
        self._subs = [session.node.create_subscription(
            msg_type, topic, lambda m, t=topic: self.counts.__setitem__(t, self.counts[t] + 1), _subscriber_qos())
            for topic in self.counts]

    def run(self, rate: float, seconds: float) -> dict:
        from rclpy.task import Future

        executor, publisher = self.session.executor, self.session.publisher(self.batch, self.joints)
        never = Future()  # spin_until_future_complete on it: the executor's own event loop, as the node runs it
        for topic in self.counts:
            self.counts[topic] = 0
        publisher.start(executor, self.prefix, rate, seconds, lambda: all(sub.get_publisher_count()
                                                                          for sub in self._subs))
        cpu = time.process_time()
        while not publisher.ready():
            executor.spin_until_future_complete(never, timeout_sec=0.05)
        sent = publisher.result()
        settle = time.monotonic() + SETTLE_SECONDS  # what is still on its way, until every message is counted
        total, moved = sum(self.counts.values()), time.monotonic()
        while (min(self.counts.values()) < sent["messages"] and (now := time.monotonic()) < settle
               and now - moved < QUIET_SECONDS):
            executor.spin_until_future_complete(never, timeout_sec=0.05)
            if sum(self.counts.values()) != total:
                total, moved = sum(self.counts.values()), time.monotonic()
        cpu = time.process_time() - cpu  # over the same span as the node's: from the go until all was counted
        return {"subscriber": "bare rclpy (EventsExecutor)", "received": min(self.counts.values()) * self.batch,
                **sent, "subscriber_cpu_seconds": cpu}

    def close(self) -> None:
        for sub in self._subs:
            self.session.node.destroy_subscription(sub)


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

    publisher = session.publisher(1, joints)
    with tempfile.TemporaryDirectory() as tmp:
        params = Path(tmp) / "joints.yaml"
        joint_state_params(params, joints, rate, _topics("/node", joints)[0])
        ident = subprocess.Popen([sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "--params-file",
                                  str(params)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            _spin_until(executor, lambda: len(statuses) == joints and all(
                int(v.get("excitation_publishers", 0)) for v in statuses.values()), 2 * MATCH_TIMEOUT)
            publisher.start(executor, "/node", rate, seconds, lambda: True)
            cpu = process_cpu_seconds(ident.pid)
            _spin_until(executor, publisher.ready, 120)
            sent = publisher.result()
            _spin_until(executor, lambda: received() >= sent["messages"], SETTLE_SECONDS + 1.0)
            end = process_cpu_seconds(ident.pid)
            sent["subscriber_cpu_seconds"] = None if cpu is None or end is None else end - cpu
        finally:
            ident.terminate()
            ident.communicate(timeout=20)
            node.destroy_subscription(diagnostics)
    return {"subscriber": "hammer_ros node", "received": received(), **sent,
            **{f"node_{what}": max((int(v.get(f"response_{what}", 0)) for v in statuses.values()), default=0)
               for what in ("dds_lost", "queue_dropped")}}


SUBSCRIBERS = ("bare", "node", "foxglove")


class ProbeSession:
    """A private ROS_DOMAIN_ID, an rclpy context and the counting node shared by many probe runs
    (``probe``), and the processes kept for all of them: one publisher per message type
    (``_Publisher``, a pair of topics per subscriber), the bare subscriber, the node and the node
    with a Foxglove client (``_NodeProcess``), each started at its first run. Their start (the
    session about 0.75 s on the 2-core bench VM, a node 2-4 s, the publisher about 1 s) is paid
    once rather than per run."""

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
        self._publishers: dict[tuple[int, int], _Publisher] = {}
        self._subscribers: dict[tuple[str, int], _BareSubscriber | _NodeProcess] = {}
        return self

    def __exit__(self, *exc) -> None:
        import rclpy

        try:
            for subscriber in self._subscribers.values():
                subscriber.close()
            for publisher in self._publishers.values():
                publisher.close()
            self.node.destroy_node()
            rclpy.try_shutdown()
        finally:
            self._stack.close()

    def publisher(self, batch: int, joints: int = 0) -> _Publisher:
        """The session's publisher of one message type (started at its first use), with topics
        under /bare, /node and /foxglove (those of a type apart from another's: ``_prefix``)."""
        if (batch, joints) not in self._publishers:
            self._publishers[batch, joints] = _Publisher(self.env, batch, [self._prefix(who, batch, joints)
                                                                            for who in SUBSCRIBERS], joints=joints)
        return self._publishers[batch, joints]

    @staticmethod
    def _prefix(who: str, batch: int, joints: int = 0) -> str:
        return f"/{who}" if joints else f"/{who}_{batch}"  # one type per topic name in a participant

    def _subscriber(self, who: str, rate: float, batch: int) -> _BareSubscriber | _NodeProcess:
        subscriber = self._subscribers.get((who, batch))
        if isinstance(subscriber, _NodeProcess) and subscriber.process.poll() is not None:  # crashed: a new one
            subscriber.close()
            subscriber = None
        if subscriber is None:
            prefix = self._prefix(who, batch)
            subscriber = (_BareSubscriber(self, prefix, batch) if who == "bare" else
                          _NodeProcess(self, f"probed_{who}_{batch}", prefix, batch, rate, who == "foxglove"))
            self._subscribers[who, batch] = subscriber
        return subscriber

    def probe(self, rates: list[float], batch: int = 1, seconds: float = 4.0, foxglove: bool = False,
              subscribers: tuple[str, ...] = ("bare", "node")) -> list[dict]:
        """Rows {subscriber, rate_msgs_per_s, batch, messages, received, lost, ...} for each rate
        and each of ``subscribers`` (SUBSCRIBERS: the bare subscriber, the node, the node with its
        Foxglove server on and one client connected); ``foxglove`` adds the last."""
        chosen = set(subscribers) | ({"foxglove"} if foxglove else set())
        rows = []
        for rate in rates:
            for who in (w for w in SUBSCRIBERS if w in chosen):
                row = self._subscriber(who, rate, batch).run(rate, seconds)
                row.update(rate_msgs_per_s=rate, batch=batch, samples_per_s=rate * batch,
                           lost=row["messages"] * batch - row["received"])
                rows.append(row)
                print(json.dumps(row), flush=True)
        return rows

    def joints_probe(self, rates: list[float], batch: int = 1, seconds: float = 4.0,
                     subscribers: tuple[str, ...] = ("bare", "node"), joints: int = 6) -> list[dict]:
        """``probe``'s rows for one JointState topic of ``joints`` named joints (one message =
        one sample per joint), read by the bare subscriber and by a fresh node of ``joints``
        channels at each rate (``_joints_node``); ``batch`` must be 1."""
        if batch != 1:
            raise ValueError(f"joints_probe: batch {batch}: a JointState carries one sample per joint")
        rows = []
        for rate in rates:
            for who in (w for w in ("bare", "node") if w in subscribers):
                if who == "bare":
                    if ("bare", -joints) not in self._subscribers:
                        self._subscribers["bare", -joints] = _BareSubscriber(self, "/bare", 1, joints)
                    row = self._subscribers["bare", -joints].run(rate, seconds)
                else:
                    row = _joints_node(self, rate, seconds, joints)
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
    parser.add_argument("--prefixes", default="", help=argparse.SUPPRESS)
    parser.add_argument("--joints", type=int, default=0,
                        help="one JointState topic of N joints read by N channels of one node (vs a bare subscriber)")
    args = parser.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    if args.publish:
        prepare_ros_environment()
        return _serve(args.batch, args.prefixes.split(","), args.plant, args.joints)
    if args.joints:
        with ProbeSession() as session:
            session.joints_probe(rates, seconds=args.seconds, joints=args.joints)
        return 0
    probe(rates, args.batch, args.seconds, args.foxglove)
    return 0


if __name__ == "__main__":
    sys.exit(main())
