"""The robot of the bad-input and shutdown tests: paper 000's G1 after F(v) = v + 4 v^3, sampled
at RATE, published from a ``ros_helpers.Listener`` as header-stamped sensor_msgs/JointState
batches (effort[:] = command on /bi/cmd, velocity[:] = response on /bi/state). The stamps are
the test's own clock (any start, any jump), so every counter of the node can be predicted."""

from __future__ import annotations

import json
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from conftest import G1
from ros_helpers import WAIT, Listener, RosProcess

from hammer_ros.identification.linear import root_rss_error
from hammer_ros.identification.simulate import HammersteinStream
from hammer_ros.ros.environment import DomainLease, child_environment

RATE = 200.0
WINDOW = 2000
NODE = {"excitation_topic": "/bi/cmd", "excitation_type": "sensor_msgs/msg/JointState", "excitation_field": "effort[:]",
        "response_topic": "/bi/state", "response_type": "sensor_msgs/msg/JointState", "response_field": "velocity[:]",
        "sample_rate": RATE, "window": WINDOW, "order": 3, "delay": 1, "solve_rate": 5.0}


def cubic(v):
    return v + 4 * v**3


def pole_error(model: dict) -> float:
    return root_rss_error(G1.poles, np.array([complex(re, im) for re, im in model["poles"]]))


class StampedPlant:
    """Publishes the plant's samples; its state and clock carry over between calls."""

    def __init__(self, listener: Listener, t0: float = 1000.0, seed: int = 1) -> None:
        self.listener = listener
        self.stream = HammersteinStream(cubic, G1)
        self.rng = np.random.default_rng(seed)
        self.t0, self.k = t0, 0
        self.last = float("nan")  # stamp of the last sample published
        self.publishers: dict[str, object] = {}
        self.create_publishers()

    def create_publishers(self) -> None:
        from sensor_msgs.msg import JointState

        for topic in (NODE["excitation_topic"], NODE["response_topic"]):
            self.publishers[topic] = self.listener.node.create_publisher(JointState, topic, 100)
        self.listener.wait_for(lambda: all(p.get_subscription_count() for p in self.publishers.values()),
                               what="the node's subscriptions")

    def destroy_publishers(self) -> None:
        for publisher in self.publishers.values():
            self.listener.node.destroy_publisher(publisher)
        self.publishers.clear()

    def take(self, n: int, constant: float | None = None):
        """(t, v, y) of the next n samples (constant = a robot standing still)."""
        v = self.rng.normal(0.0, 0.3, n) if constant is None else np.full(n, constant)
        y = self.stream(v) + 0.01 * self.rng.normal(size=n)
        t = self.t0 + (self.k + np.arange(n)) / RATE
        self.k += n
        return t, v, y

    def publish(self, t, v, y, batch: int = 100, name: list[str] | None = None) -> None:
        """Both streams, ``batch`` samples per message stamped by its last sample."""
        from sensor_msgs.msg import JointState

        self.last = float(t[-1])
        for start in range(0, t.size, batch):
            stop = min(t.size, start + batch)
            ns = int(round(t[stop - 1] * 1e9))
            for topic, field, values in ((NODE["excitation_topic"], "effort", v), (NODE["response_topic"], "velocity",
                                                                                   y)):
                msg = JointState()
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
                msg.name = list(name or [])
                setattr(msg, field, [float(x) for x in values[start:stop]])
                self.publishers[topic].publish(msg)
            self.listener.executor.spin_once(timeout_sec=0.002)  # paces the sender, keeps the listener current

    def send(self, n: int, constant: float | None = None) -> np.ndarray:
        t, v, y = self.take(n, constant)
        self.publish(t, v, y)
        return t


class Observer:
    """Every ~/model (not only the latched last one) and every /diagnostics status of the node."""

    def __init__(self, listener: Listener) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import String

        self.listener = listener
        self.models: list[dict] = []
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        listener.node.create_subscription(String, "/hammer_ros/model", lambda m: self.models.append(json.loads(m.data)),
                                          qos)
        self.diagnostics = listener.subscribe_diagnostics()

    def count(self, key: str) -> int:
        return int(float(self.diagnostics[-1][key])) if self.diagnostics else 0

    def counts(self, *keys: str) -> dict[str, int]:
        return {k: self.count(k) for k in keys}

    def settle(self, stamp: float, timeout: float = WAIT) -> dict:
        """The first diagnostics after the node took in both streams up to ``stamp`` (the last
        sample sent): from then on its counters include everything sent."""
        def caught_up():
            d = self.diagnostics[-1] if self.diagnostics else {}
            return all(abs(float(d.get(f"last_stamp_{s}", "nan")) - stamp) < 1e-6 for s in ("excitation", "response"))

        try:
            return self.listener.wait_for(lambda: caught_up() and self.diagnostics[-1], timeout,
                                          what=f"the node at stamp {stamp}")
        except AssertionError as exc:  # say where the node stood (what it received, lost, dropped)
            d = self.diagnostics[-1] if self.diagnostics else {}
            words = ("stamp", "received", "missing", "lost", "dropped")
            seen = {k: v for k, v in d.items() if any(w in k for w in words)}
            raise AssertionError(f"{exc}; {len(self.diagnostics)} diagnostics, the last: {seen}") from None

    def next_solve(self) -> dict:
        seen = len(self.diagnostics)
        return self.listener.wait_for(lambda: len(self.diagnostics) > seen and self.diagnostics[-1],
                                      what="the next solve's diagnostics")

    def fresh_model(self, stamp: float, timeout: float = 30.0) -> dict:
        """The first fresh model (not stale) solved on a full window ending at ``stamp``."""
        def found():
            return next((m for m in reversed(self.models) if not m.get("stale") and m["samples"] == WINDOW
                         and m["stamp"] is not None and abs(m["stamp"] - stamp) < 1e-6), None)

        return self.listener.wait_for(found, timeout=timeout, what=f"a fresh model on the window ending at {stamp}")


@contextmanager
def stamped_node(logs: Path, parameters: dict) -> Iterator[Listener]:
    """A node with ``parameters`` on a private ROS_DOMAIN_ID and a listener in this process that
    feeds it (``plant``: StampedPlant) and watches it (``observer``: Observer; ``process``: the
    node's RosProcess, ``env``: its environment); the node must exit 0 on SIGINT at the end."""
    with DomainLease() as lease:
        env = child_environment(lease.domain_id, log_dir=logs / "ros_log")
        node = RosProcess("hammer_ros.ros.node", parameters, env, logs / "node.log")
        listener = Listener(env)
        try:
            listener.observer = Observer(listener)
            listener.plant = StampedPlant(listener)
            listener.process = node
            listener.env = env
            yield listener
        finally:
            listener.close()
            code = node.stop(signal.SIGINT)
            assert code == 0, node.output()[-3000:]
