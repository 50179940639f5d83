"""A session of the rate probe (``hammer_ros.tools.ros_rate_probe``): a private ROS_DOMAIN_ID, an
rclpy context and the processes kept for every run (publishers, the bare subscriber, nodes)."""

from __future__ import annotations

import contextlib
import json
import os

from .environment import DomainLease, child_environment, prepare_ros_environment
from .rate_probe_node import NodeProcess, joints_node
from .rate_probe_publisher import PublisherProcess
from .rate_probe_subscriber import BareSubscriber

SUBSCRIBERS = ("bare", "node", "foxglove")


class ProbeSession:
    """A private ROS_DOMAIN_ID, an rclpy context and the counting node shared by many probe runs
    (``probe``), and the processes kept for all of them: one publisher per message type
    (``PublisherProcess``, a pair of topics per subscriber), the bare subscriber, the node and the node
    with a Foxglove client (``NodeProcess``), each started at its first run. Their start (the
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
        self._publishers: dict[tuple[int, int], PublisherProcess] = {}
        self._subscribers: dict[tuple[str, int], BareSubscriber | NodeProcess] = {}
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

    def publisher(self, batch: int, joints: int = 0) -> PublisherProcess:
        """The session's publisher of one message type (started at its first use), with topics
        under /bare, /node and /foxglove (those of a type apart from another's: ``_prefix``)."""
        if (batch, joints) not in self._publishers:
            self._publishers[batch, joints] = PublisherProcess(self.env, batch, [self._prefix(who, batch, joints)
                                                                            for who in SUBSCRIBERS], joints=joints)
        return self._publishers[batch, joints]

    @staticmethod
    def _prefix(who: str, batch: int, joints: int = 0) -> str:
        return f"/{who}" if joints else f"/{who}_{batch}"  # one type per topic name in a participant

    def _subscriber(self, who: str, rate: float, batch: int) -> BareSubscriber | NodeProcess:
        subscriber = self._subscribers.get((who, batch))
        if isinstance(subscriber, NodeProcess) and subscriber.process.poll() is not None:  # crashed: a new one
            subscriber.close()
            subscriber = None
        if subscriber is None:
            prefix = self._prefix(who, batch)
            subscriber = (BareSubscriber(self, prefix, batch) if who == "bare" else
                          NodeProcess(self, f"probed_{who}_{batch}", prefix, batch, rate, who == "foxglove"))
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
        channels at each rate (``joints_node``); ``batch`` must be 1."""
        if batch != 1:
            raise ValueError(f"joints_probe: batch {batch}: a JointState carries one sample per joint")
        rows = []
        for rate in rates:
            for who in (w for w in ("bare", "node") if w in subscribers):
                if who == "bare":
                    if ("bare", -joints) not in self._subscribers:
                        self._subscribers["bare", -joints] = BareSubscriber(self, "/bare", 1, joints)
                    row = self._subscribers["bare", -joints].run(rate, seconds)
                else:
                    row = joints_node(self, rate, seconds, joints)
                row.update(rate_msgs_per_s=rate, batch=1, joints=joints, samples_per_s=rate,
                           lost=row["messages"] - row["received"])
                rows.append(row)
                print(json.dumps(row), flush=True)
        return rows
