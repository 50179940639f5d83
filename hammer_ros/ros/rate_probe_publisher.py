"""The publisher of the rate probe (``hammer_ros.tools.ros_rate_probe``): a process of its own
(``serve``, ``python -m hammer_ros.ros.rate_probe_publisher``) that sends R messages/s on each
subscriber's pair of topics on a ``Schedule``, driven line by line over its stdin/stdout by
``PublisherProcess``; the timing constants the probe's subscribers share; ``ProbeContext``, what
a subscriber of a session needs from it."""

from __future__ import annotations

import argparse
import json
import select
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from .environment import prepare_ros_environment

TOPICS = ("/command", "/response")
JOINT_TOPIC = "/joint_states"  # ``--joints N``: one JointState of N named joints (position u, velocity y)
MATCH_TIMEOUT = 15.0
PUBLISHER_MATCH_TIMEOUT = 2 * MATCH_TIMEOUT  # the publisher starts beside a node that starts up (``_node``)
SETTLE_SECONDS = 1.0
MAX_LAG = 0.02  # s behind its schedule at which the publisher counts a stall and resumes without a burst
PLANT_MESSAGES = 64  # distinct (u, y) message pairs cycled by a --plant publisher


def _plant_messages(batch: int) -> list[tuple]:
    """(u, y) Float64MultiArray pairs of paper 000's G1 with tanh(8v)/8, one continuous record."""
    from std_msgs.msg import Float64MultiArray

    from ..identification.simulate import HammersteinStream
    from ..reproduce.cls import G1, INPUT_STD, NONLINEARITIES

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


def joint_state(joints: int):
    """The JointState of the ``--joints`` runs: joints joint_0.. with positions and velocities."""
    from sensor_msgs.msg import JointState

    values = [float(i) / joints for i in range(joints)]
    return JointState(name=[f"joint_{i}" for i in range(joints)], position=values, velocity=values)


def serve(batch: int, prefixes: list[str], plant: bool = False, joints: int = 0) -> int:
    """Publisher process of a probe session: publishers of every prefix's topics (``probe_topics``).
    For each command line on stdin ({"prefix", "rate", "seconds"}) it waits for a subscriber on
    that prefix's topics, says so ({"matched": bool}), waits for the go (a line:
    ``PublisherProcess.start``), publishes on a ``Schedule`` and prints the count sent and the stalls;
    it exits at the end of its input. The same message every time, or (``plant``) a Hammerstein
    record cycled. Without the schedule's restart, a 0.3 s stall at 7000/s was a catch-up burst of
    about 2000 messages per topic, more than a subscriber's history holds: a loss of the
    publisher's making."""
    import rclpy
    from std_msgs.msg import Float64, Float64MultiArray

    rclpy.init()
    node = rclpy.create_node("rate_probe_publisher")
    msg_type = type(joint_state(joints)) if joints else Float64 if batch == 1 else Float64MultiArray
    pubs = {prefix: [node.create_publisher(msg_type, topic, 1000) for topic in probe_topics(prefix, joints)]
            for prefix in prefixes}
    values = [float(i % 97) / 97.0 for i in range(batch)]
    message = Float64(data=0.5) if batch == 1 else Float64MultiArray(data=values)
    pairs = _plant_messages(batch) if plant else [(joint_state(joints),)] if joints else [(message, message)]
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


def probe_topics(prefix: str, joints: int = 0) -> list[str]:
    """The topics of one subscriber of a session: ``prefix`` + TOPICS, or + JOINT_TOPIC."""
    return [prefix + JOINT_TOPIC] if joints else [prefix + topic for topic in TOPICS]


def spin_until(executor, done, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return done()


class PublisherProcess:
    """The publisher process (``serve``) of a probe session, started once for all its runs, with
    one pair of topics per subscriber (``prefixes``): only the subscriber of a run receives it,
    and no run pays for a process start and discovery."""

    def __init__(self, env: dict, batch: int, prefixes: list[str], plant: bool = False, joints: int = 0) -> None:
        cmd = [sys.executable, "-m", "hammer_ros.ros.rate_probe_publisher", "--batch", str(batch),
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
        spin_until(executor, subscribed, MATCH_TIMEOUT)
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


class ProbeContext(Protocol):
    """What a subscriber of a probe session uses (``rate_probe_session.ProbeSession``): the
    counting node and its executor, the children's environment and the session's publishers."""

    node: Any
    executor: Any
    env: dict

    def publisher(self, batch: int, joints: int = 0) -> PublisherProcess: ...


def main(argv: list[str] | None = None) -> int:
    """The publisher process (``PublisherProcess`` starts it)."""
    parser = argparse.ArgumentParser(prog="python -m hammer_ros.ros.rate_probe_publisher")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--prefixes", default="")
    parser.add_argument("--plant", action="store_true")
    parser.add_argument("--joints", type=int, default=0)
    args = parser.parse_args(argv)
    prepare_ros_environment()
    return serve(args.batch, args.prefixes.split(","), args.plant, args.joints)


if __name__ == "__main__":
    sys.exit(main())
