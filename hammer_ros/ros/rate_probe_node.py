"""The node side of the rate probe (``hammer_ros.tools.ros_rate_probe``): ``hammer-ros node``
processes started and driven over ROS (``NodeProcess``: parameters, ``~/reset``, its
/diagnostics counters; with a Foxglove client counting the dashboard's messages), a node of N
JointState channels (``joints_node``) and the node's memory under load (``node_memory``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

from ..process_status import child_pids, process_cpu_seconds, process_pss_kib, process_status_kib, process_tree
from .environment import DomainLease, child_environment, prepare_ros_environment
from .rate_probe_publisher import (
    JOINT_TOPIC,
    MATCH_TIMEOUT,
    SETTLE_SECONDS,
    ProbeContext,
    PublisherProcess,
    probe_topics,
    spin_until,
)

QUIET_UPDATES = 3
RESEND = 2.0  # s without a service response before the request is sent again (``call_service``)


class DiagnosticUpdates(list):
    """The node's received-sample count (the lower of its two inputs') at each /diagnostics."""

    def settled(self, since: int) -> bool:
        """The last QUIET_UPDATES counts after the first ``since`` are the same: nothing more arrives."""
        last = self[since:][-QUIET_UPDATES:]
        return len(last) == QUIET_UPDATES and len(set(last)) == 1


def diagnostics_counters(node, name: str = "hammer_ros"):
    """Subscribe to /diagnostics: the status of the node ``name`` (its key/value pairs, updated in
    place) and the received count at each of its messages (``DiagnosticUpdates``)."""
    from diagnostic_msgs.msg import DiagnosticArray

    latest: dict[str, str] = {}
    updates = DiagnosticUpdates()

    def on_diagnostics(msg) -> None:
        for status in msg.status:
            if status.hardware_id == name:
                latest.update({kv.key: kv.value for kv in status.values})
                updates.append(min(int(latest.get(k, 0)) for k in ("received_excitation", "received_response")))

    return latest, updates, node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)


def node_subscribed(latest: dict[str, str]) -> bool:
    """The node's latest /diagnostics has a matched publisher on both inputs."""
    return all(int(latest.get(f"{stream}_publishers", 0)) > 0 for stream in ("excitation", "response"))


def start_node(env: dict, params: list[str], batch: int, prefix: str = "", name: str = "hammer_ros",
                stderr=subprocess.PIPE) -> subprocess.Popen:
    """A fresh ``hammer-ros node`` called ``name`` on ``prefix`` + TOPICS (Float64 or
    Float64MultiArray ``data[:]``)."""
    field = "data" if batch == 1 else "data[:]"
    type_name = "std_msgs/msg/Float64" if batch == 1 else "std_msgs/msg/Float64MultiArray"
    for stream, topic in zip(("excitation", "response"), probe_topics(prefix)):
        params = [*params, f"{stream}_topic:={topic}", f"{stream}_type:={type_name}", f"{stream}_field:={field}"]
    cmd = [sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "-r", f"__node:={name}",
           *[a for p in params for a in ("-p", p)]]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=stderr, text=True)


class FoxgloveClient:
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


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def call_service(executor, request: Callable[[], Any], what: str, timeout: float = 2 * MATCH_TIMEOUT):
    """The result of a service request (a callable making its future: idempotent), sent again
    every RESEND s without a response (Fast DDS drops a response whose reader it has not matched
    yet); RuntimeError after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        future = request()
        if spin_until(executor, future.done, min(RESEND, deadline - time.monotonic())):
            return future.result()
    raise RuntimeError(f"no response to {what} in {timeout:g} s")


class NodeProcess:
    """A ``hammer-ros node`` called ``name`` on ``prefix``'s topics (window 4000, cls-markov, 4
    solves/s; with ``foxglove`` its Foxglove server on and one client subscribed to every channel),
    kept for every run of a session. Before a run its sample rate is set (SetParameters) and its
    window reset (``~/reset``: the engine and its counters start at 0, as a fresh node's), after it
    reset again (so that it solves on an empty window while another subscriber's run goes on)."""

    def __init__(self, session: ProbeContext, name: str, prefix: str, batch: int, rate: float,
                 foxglove: bool = False) -> None:
        import tempfile

        from rclpy.parameter_client import AsyncParameterClient
        from std_srvs.srv import Trigger

        self.session, self.name, self.prefix, self.batch, self.rate = session, name, prefix, batch, rate
        self.latest, self.updates, self._sub = diagnostics_counters(session.node, name)
        self._stderr = tempfile.TemporaryFile("w+")  # not a pipe: nobody reads it while the node runs
        port = free_port() if foxglove else 0
        self.process = start_node(session.env, [f"sample_rate:={rate * batch}", "solve_rate:=4.0", "window:=4000",
                                                 f"foxglove_port:={port}"], batch, prefix, name, self._stderr)
        self._parameters = AsyncParameterClient(session.node, name)
        self._reset = session.node.create_client(Trigger, f"/{name}/reset")
        self._trigger = Trigger.Request
        self.client = None
        spin_until(session.executor, lambda: bool(self.latest) or self.process.poll() is not None,
                    MATCH_TIMEOUT)  # up: diagnostics
        if self.error() is None and foxglove:
            self.client = FoxgloveClient(port)
            spin_until(session.executor, lambda: self.client.messages > 0, MATCH_TIMEOUT)  # connected, receiving

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
        call_service(self.session.executor, lambda: self._reset.call_async(self._trigger()), f"/{self.name}/reset")

    def prepare(self, rate: float) -> str | None:
        """Set the sample rate of a run at ``rate`` messages/s and reset the window; why not, or None."""
        from rclpy.parameter import Parameter

        if rate != self.rate:
            [result] = call_service(self.session.executor, lambda: self._parameters.set_parameters(
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
        publisher.start(executor, self.prefix, rate, seconds, lambda: node_subscribed(self.latest))
        cpu = process_cpu_seconds(self.process.pid)
        spin_until(executor, publisher.ready, 120)
        sent = publisher.result()
        expected, since = sent["messages"] * self.batch, len(self.updates)
        spin_until(executor, lambda: self.received() >= expected or self.updates.settled(since),
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
        latest, _, _ = diagnostics_counters(node)
        diagnoses: list[int] = []
        node.create_subscription(String, "/hammer_ros/diagnosis",
                                 lambda m: diagnoses.append(json.loads(m.data).get("samples", 0)), 10)
        params = [f"sample_rate:={rate * batch}", f"window:={window}", "solve_rate:=1.0", "diagnosis_period:=2.0",
                  "max_gap:=1.0"]
        ident, publisher = start_node(env, params, batch), None
        try:
            if not spin_until(executor, lambda: bool(latest), MATCH_TIMEOUT):
                raise RuntimeError("the node published no diagnostics")
            idle = process_status_kib("VmRSS", ident.pid)
            seconds = 1.2 * window / (rate * batch) + 1.0
            publisher = PublisherProcess(env, batch, [""], plant=True)
            publisher.start(executor, "", rate, seconds, lambda: node_subscribed(latest))
            full = lambda: int(latest.get("window_samples", 0)) >= window  # noqa: E731
            spin_until(executor, lambda: full() or publisher.ready(), seconds + MATCH_TIMEOUT)
            def attempts() -> int:
                return int(latest.get("solves", 0)) + int(latest.get("solve_errors", 0))

            diagnosed = min(window, PARAMETERS["diagnosis_window"].default)
            solves = attempts()
            done = spin_until(executor, lambda: attempts() >= solves + 2 and max(diagnoses, default=0) >= diagnosed,
                               120)
            peak = process_status_kib("VmHWM", ident.pid)
            workers = 0
            for child in child_pids(ident.pid):  # its solver and diagnosis processes
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


def joint_state_params(path, joints: int, rate: float, topic: str = JOINT_TOPIC,
                       diagnosis_period: float = 30.0) -> None:
    """A node params file of ``joints`` channels joint_0.. over ``topic`` (u = position[joint_k],
    y = velocity[joint_k]), each diagnosing every ``diagnosis_period`` s."""
    lines = ["hammer_ros:", "  ros__parameters:", f"    excitation_topic: {topic}",
             "    excitation_type: sensor_msgs/msg/JointState", f"    response_topic: {topic}",
             "    response_type: sensor_msgs/msg/JointState", f"    sample_rate: {float(rate)}", "    solve_rate: 4.0",
             "    window: 4000",
             f"    diagnosis_period: {float(diagnosis_period)}",
             f"    channels: [{', '.join(f'joint_{k}' for k in range(joints))}]"]
    lines += [f'    joint_{k}: {{excitation_field: "position[joint_{k}]", response_field: "velocity[joint_{k}]"}}'
              for k in range(joints)]
    path.write_text("\n".join(lines) + "\n")


def joints_node_memory(joints: int, settle: float = 3.0, diagnosis_period: float = 30.0,
                       pythonpath: str | None = None) -> dict:
    """A fresh node of ``joints`` JointState channels (``joint_state_params``; no publisher: idle):
    ``start_seconds`` from its launch until /diagnostics carries every channel's status, then,
    ``settle`` s later, its processes (the node and every process it started, ``process_tree``)
    with the sum of their resident (VmRSS) and proportional (Pss: shared pages counted once)
    sizes. ``pythonpath``: the node's PYTHONPATH (another checkout's code, side by side)."""
    import tempfile
    from pathlib import Path

    prepare_ros_environment()
    with DomainLease() as lease, tempfile.TemporaryDirectory() as tmp:
        env = child_environment(lease.domain_id)
        if pythonpath is not None:
            env["PYTHONPATH"] = pythonpath
        os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTRTPS_DEFAULT_PROFILES_FILE")})
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.experimental import EventsExecutor
        from rclpy.signals import SignalHandlerOptions

        context = rclpy.Context()
        rclpy.init(context=context, domain_id=lease.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("memory_probe", context=context)
        executor = EventsExecutor(context=context)
        executor.add_node(node)
        names: set[str] = set()
        node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: names.update(s.name for s in m.status), 10)
        params = Path(tmp) / "joints.yaml"
        joint_state_params(params, joints, 1000.0, diagnosis_period=diagnosis_period)
        started = time.monotonic()
        ident = subprocess.Popen([sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "--params-file",
                                  str(params)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            if not spin_until(executor, lambda: len(names) >= joints or ident.poll() is not None, 120):
                raise RuntimeError(f"the node published no /diagnostics of its {joints} channels in 120 s")
            if ident.poll() is not None:
                raise RuntimeError(f"the node exited {ident.returncode}: {ident.stderr.read()[-300:]}")
            start_seconds = time.monotonic() - started
            spin_until(executor, lambda: False, settle)
            processes = []
            for pid in process_tree(ident.pid):
                try:
                    processes.append({"pid": pid, "name": Path(f"/proc/{pid}/comm").read_text().strip(),
                                      "rss_kib": process_status_kib("VmRSS", pid), "pss_kib": process_pss_kib(pid)})
                except (RuntimeError, OSError):  # gone meanwhile
                    continue
        finally:
            ident.terminate()
            ident.communicate(timeout=30)
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=context)
    return {"joints": joints, "start_seconds": start_seconds, "processes": len(processes),
            "rss_kib": sum(p["rss_kib"] for p in processes), "pss_kib": sum(p["pss_kib"] for p in processes),
            "each": processes}


def joints_node(session: ProbeContext, rate: float, seconds: float, joints: int) -> dict:
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
        joint_state_params(params, joints, rate, probe_topics("/node", joints)[0])
        ident = subprocess.Popen([sys.executable, "-m", "hammer_ros.ros.node", "--ros-args", "--params-file",
                                  str(params)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            spin_until(executor, lambda: len(statuses) == joints and all(
                int(v.get("excitation_publishers", 0)) for v in statuses.values()), 2 * MATCH_TIMEOUT)
            publisher.start(executor, "/node", rate, seconds, lambda: True)
            cpu = process_cpu_seconds(ident.pid)
            spin_until(executor, publisher.ready, 120)
            sent = publisher.result()
            spin_until(executor, lambda: received() >= sent["messages"], SETTLE_SECONDS + 1.0)
            end = process_cpu_seconds(ident.pid)
            sent["subscriber_cpu_seconds"] = None if cpu is None or end is None else end - cpu
        finally:
            ident.terminate()
            ident.communicate(timeout=20)
            node.destroy_subscription(diagnostics)
    return {"subscriber": "hammer_ros node", "received": received(), **sent,
            **{f"node_{what}": max((int(v.get(f"response_{what}", 0)) for v in statuses.values()), default=0)
               for what in ("dds_lost", "queue_dropped")}}
