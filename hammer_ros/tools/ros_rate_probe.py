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

The rclpy parts live in ``hammer_ros.ros``, by role: ``rate_probe_publisher`` (the publisher
process, ``Schedule``), ``rate_probe_subscriber`` (the bare subscriber), ``rate_probe_node`` (the
node processes, ``node_memory``) and ``rate_probe_session`` (``ProbeSession``); this module is
the command line over them.
"""

from __future__ import annotations

import argparse
import sys

from ..ros.rate_probe_node import node_memory
from ..ros.rate_probe_publisher import MAX_LAG, Schedule
from ..ros.rate_probe_session import ProbeSession

__all__ = ["MAX_LAG", "ProbeSession", "Schedule", "main", "node_memory", "probe"]


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
    parser.add_argument("--joints", type=int, default=0,
                        help="one JointState topic of N joints read by N channels of one node (vs a bare subscriber)")
    args = parser.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    if args.joints:
        with ProbeSession() as session:
            session.joints_probe(rates, seconds=args.seconds, joints=args.joints)
        return 0
    probe(rates, args.batch, args.seconds, args.foxglove)
    return 0


if __name__ == "__main__":
    sys.exit(main())
