"""The bare rclpy subscriber of the rate probe (``hammer_ros.tools.ros_rate_probe``): the
reference the node's rate is measured against, with the node's QoS and its executor's loop."""

from __future__ import annotations

import time

from .rate_probe_publisher import SETTLE_SECONDS, ProbeContext, joint_state, probe_topics

# A subscriber that lost samples never counts them all: the wait for the rest ends once nothing has come
# for QUIET_SECONDS (bare), or over QUIET_UPDATES /diagnostics of the node (4 a second) in a row.
QUIET_SECONDS = 0.3


def subscriber_qos():
    """What the node subscribes with: best effort, its default ``qos_depth``."""
    from rclpy.qos import QoSProfile, qos_profile_sensor_data

    from ..ros.node_core import PARAMETERS

    return QoSProfile(depth=PARAMETERS["qos_depth"].default, reliability=qos_profile_sensor_data.reliability,
                      durability=qos_profile_sensor_data.durability)


class BareSubscriber:
    """The bare rclpy subscriber of a session (this process, EventsExecutor running its own loop,
    as the node; the node's QoS), counting the messages of each of ``prefix``'s topics; kept for
    every run (idle while another subscriber's run goes on: nothing is published on its topics)."""

    def __init__(self, session: ProbeContext, prefix: str, batch: int, joints: int = 0) -> None:
        from std_msgs.msg import Float64, Float64MultiArray

        self.session, self.prefix, self.batch, self.joints = session, prefix, batch, joints
        msg_type = type(joint_state(joints)) if joints else Float64 if batch == 1 else Float64MultiArray
        self.counts = dict.fromkeys(probe_topics(prefix, joints), 0)
        self._subs = [session.node.create_subscription(
            msg_type, topic, lambda m, t=topic: self.counts.__setitem__(t, self.counts[t] + 1), subscriber_qos())
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
