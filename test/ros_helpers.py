"""Helpers for tests with real ROS 2 processes: start/stop nodes, and a listener node in the
test process (its own rclpy Context on the test's ROS_DOMAIN_ID) that waits for messages with a
timeout instead of sleeping."""

from __future__ import annotations

import json
import os
import signal
import socket
import time
from collections.abc import Callable
from pathlib import Path

from hammer_ros.tools.processes import start_ros_process, stop_process


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]

RESEND = 5.0  # s without a response before an idempotent request is sent again
WAIT = 30.0  # s: generous bound for anything that normally takes < 2 s on a loaded 2-core machine
STOP_TIMEOUT = 10.0


class RosProcess:
    """A ``python -m MODULE [OPTIONS] --ros-args -p ...`` child with its output in a log file."""

    def __init__(self, module: str, parameters: dict, env: dict, log: Path, options: tuple[str, ...] = (),
                 params_file: Path | None = None) -> None:
        self.log = log
        self.process = start_ros_process(module, parameters, env, log, options=options, params_file=params_file)

    def stop(self, sig: int = signal.SIGINT, timeout: float = STOP_TIMEOUT) -> int:
        """Send ``sig`` and wait; a process that does not exit is killed and reported as -9."""
        return stop_process(self.process, (sig,), timeout)

    def output(self) -> str:
        return self.log.read_text(errors="replace")


class Listener:
    """An rclpy node in the test process on ``env``'s ROS_DOMAIN_ID."""

    def __init__(self, env: dict, name: str = "test_listener") -> None:
        for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTRTPS_DEFAULT_PROFILES_FILE", "AMENT_PREFIX_PATH"):
            if key in env:
                os.environ[key] = env[key]
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(env["ROS_DOMAIN_ID"]),
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def latched_qos(self):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

    def subscribe_json(self, topic: str, latched: bool = True) -> list[dict]:
        """Every std_msgs/String JSON message on ``topic``, appended to the returned list."""
        from std_msgs.msg import String

        received: list[dict] = []
        self.node.create_subscription(String, topic, lambda m: received.append(json.loads(m.data)),
                                      self.latched_qos() if latched else 10)
        return received

    def subscribe_diagnostics(self, node_name: str = "hammer_ros") -> list[dict]:
        """Status values (key -> str) plus ``level``/``message`` of ``node_name``'s diagnostics."""
        from diagnostic_msgs.msg import DiagnosticArray

        received: list[dict] = []

        def on_message(msg) -> None:
            for status in msg.status:
                if status.name.startswith(node_name):
                    values = {kv.key: kv.value for kv in status.values}
                    values.update(level=status.level[0], message=status.message)
                    received.append(values)

        self.node.create_subscription(DiagnosticArray, "/diagnostics", on_message, 10)
        return received

    def wait_for(self, condition: Callable[[], object], timeout: float = WAIT, what: str = "condition"):
        """Spin until ``condition()`` is truthy and return it; AssertionError after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = condition()
            if value:
                return value
            self.executor.spin_once(timeout_sec=0.05)
        raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")

    def wait_future(self, future, timeout: float = WAIT, what: str = "a service response"):
        """Spin until ``future`` is done and return its result. Given a callable making the future
        (an idempotent request), resend it every ``RESEND`` s without a response: Fast DDS drops a
        response whose reader it has not matched yet ("failed to send response (timeout)"). Every
        request sent stays awaited: the first answer counts, also one that takes longer than RESEND (a
        diagnosis on a loaded machine), which a resend must not discard."""
        request = future if callable(future) else None
        deadline = time.monotonic() + timeout
        sent = [] if request else [future]
        while True:
            if request:
                sent.append(request())
            left = deadline - time.monotonic()
            try:
                self.wait_for(lambda: any(f.done() for f in sent), min(left, RESEND) if request else left, what)
                return next(f for f in sent if f.done()).result()
            except AssertionError:
                if not request or time.monotonic() >= deadline:
                    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}") from None

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
