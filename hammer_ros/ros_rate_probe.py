"""How many messages per second reach a subscriber without loss: the hammer_ros node vs a bare
rclpy subscriber (EventsExecutor in a spin_once loop), on a private ROS_DOMAIN_ID on loopback.

    python -m hammer_ros.ros_rate_probe [--rates 1000,5000,10000] [--batch 1] [--seconds 4]

For each rate R a publisher process sends R messages/s on each of /command and /response
(std_msgs/Float64, or Float64MultiArray of ``--batch`` samples; reliable, depth 1000) for
``--seconds`` seconds, once to a bare subscriber (this process, with the node's QoS: best
effort, depth 1000) and once to a fresh
``hammer-ros node`` (whose /diagnostics counters are read back). A rate is sustained when every
published sample was received. Output: one JSON document per line on stdout. Reusable by
``hammer-ros bench`` through :func:`probe`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from .ros_env import DomainLease, child_environment, prepare_ros_environment

TOPICS = ("/command", "/response")
MATCH_TIMEOUT = 15.0
SETTLE_SECONDS = 1.0


def _publish(rate: float, seconds: float, batch: int) -> int:
    """Publisher process: wait for a subscriber on both topics, publish, print the count sent."""
    import rclpy
    from std_msgs.msg import Float64, Float64MultiArray

    rclpy.init()
    node = rclpy.create_node("rate_probe_publisher")
    msg_type = Float64 if batch == 1 else Float64MultiArray
    pubs = [node.create_publisher(msg_type, topic, 1000) for topic in TOPICS]
    deadline = time.monotonic() + MATCH_TIMEOUT
    while any(p.get_subscription_count() == 0 for p in pubs) and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.5)  # let the subscriber finish matching both topics
    values = [float(i % 97) / 97.0 for i in range(batch)]
    message = Float64(data=0.5) if batch == 1 else Float64MultiArray(data=values)
    total = int(rate * seconds)
    start = time.monotonic()
    sent = 0
    while sent < total:
        due = min(total, int((time.monotonic() - start) * rate) + 1)
        while sent < due:
            for pub in pubs:
                pub.publish(message)
            sent += 1
        time.sleep(max(0.0, start + sent / rate - time.monotonic()))
    elapsed = time.monotonic() - start
    print(json.dumps({"messages": sent, "publish_seconds": elapsed}), flush=True)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _start_publisher(env: dict, rate: float, seconds: float, batch: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "hammer_ros.ros_rate_probe", "--publish", "--rates", str(rate),
           "--seconds", str(seconds), "--batch", str(batch)]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)


def _finish(publisher: subprocess.Popen) -> dict:
    out, _ = publisher.communicate(timeout=120)
    return json.loads(out.strip().splitlines()[-1])


def _bare(node, executor, env: dict, rate: float, seconds: float, batch: int) -> dict:
    """Count messages in this process (EventsExecutor + spin_once)."""
    from std_msgs.msg import Float64, Float64MultiArray

    counts = {topic: 0 for topic in TOPICS}
    msg_type = Float64 if batch == 1 else Float64MultiArray
    from rclpy.qos import QoSProfile, qos_profile_sensor_data

    qos = QoSProfile(depth=1000, reliability=qos_profile_sensor_data.reliability,
                     durability=qos_profile_sensor_data.durability)  # what the node subscribes with
    subs = [node.create_subscription(msg_type, topic, lambda m, t=topic: counts.__setitem__(t, counts[t] + 1), qos)
            for topic in TOPICS]
    publisher = _start_publisher(env, rate, seconds, batch)
    while publisher.poll() is None:
        executor.spin_once(timeout_sec=0.05)
    settle = time.monotonic() + SETTLE_SECONDS
    while time.monotonic() < settle:
        executor.spin_once(timeout_sec=0.05)
    for sub in subs:
        node.destroy_subscription(sub)
    sent = _finish(publisher)
    return {"subscriber": "bare rclpy (EventsExecutor spin_once)", "received": min(counts.values()) * batch, **sent}


def _node(node, executor, env: dict, rate: float, seconds: float, batch: int) -> dict:
    """Run a fresh hammer_ros node and read its received-sample counters from /diagnostics."""
    from diagnostic_msgs.msg import DiagnosticArray

    latest: dict[str, str] = {}

    def on_diagnostics(msg) -> None:
        for status in msg.status:
            if status.name.startswith("hammer_ros"):
                latest.update({kv.key: kv.value for kv in status.values})

    sub = node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    field = "data" if batch == 1 else "data[:]"
    type_name = "std_msgs/msg/Float64" if batch == 1 else "std_msgs/msg/Float64MultiArray"
    params = [f"sample_rate:={rate * batch}", "solve_rate:=4.0", "window:=4000"]
    for stream, topic in zip(("excitation", "response"), TOPICS):
        params += [f"{stream}_topic:={topic}", f"{stream}_type:={type_name}", f"{stream}_field:={field}"]
    cmd = [sys.executable, "-m", "hammer_ros.node", "--ros-args", *[a for p in params for a in ("-p", p)]]
    ident = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + MATCH_TIMEOUT
        while not latest and time.monotonic() < deadline:  # the node is up once it publishes diagnostics
            executor.spin_once(timeout_sec=0.05)
        publisher = _start_publisher(env, rate, seconds, batch)
        while publisher.poll() is None:
            executor.spin_once(timeout_sec=0.05)
        sent = _finish(publisher)
        expected = sent["messages"] * batch
        settle = time.monotonic() + SETTLE_SECONDS + 1.0
        while time.monotonic() < settle and min(int(latest.get(k, 0)) for k in (
                "received_excitation", "received_response")) < expected:
            executor.spin_once(timeout_sec=0.05)
    finally:
        ident.terminate()
        ident.communicate(timeout=10)
        node.destroy_subscription(sub)
    received = min(int(latest.get(k, 0)) for k in ("received_excitation", "received_response"))
    return {"subscriber": "hammer_ros node", "received": received, "aligned": int(latest.get("aligned", 0)), **sent}


def probe(rates: list[float], batch: int = 1, seconds: float = 4.0) -> list[dict]:
    """Rows {subscriber, rate_msgs_per_s, batch, messages, received, lost, ...} for each rate."""
    prepare_ros_environment()
    rows = []
    with DomainLease() as lease:
        env = child_environment(lease.domain_id)
        os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                               "FASTRTPS_DEFAULT_PROFILES_FILE")})
        import rclpy
        from rclpy.experimental import EventsExecutor

        rclpy.init()
        node = rclpy.create_node("rate_probe")
        executor = EventsExecutor()
        executor.add_node(node)
        try:
            for rate in rates:
                for measure in (_bare, _node):
                    row = measure(node, executor, env, rate, seconds, batch)
                    row.update(rate_msgs_per_s=rate, batch=batch, samples_per_s=rate * batch,
                               lost=row["messages"] * batch - row["received"])
                    rows.append(row)
                    print(json.dumps(row), flush=True)
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hammer_ros.ros_rate_probe", description=__doc__.split("\n")[0])
    parser.add_argument("--rates", default="1000,2000,5000,10000", help="messages/s per topic, comma-separated")
    parser.add_argument("--batch", type=int, default=1, help="samples per message (1 = Float64)")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--publish", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    if args.publish:
        prepare_ros_environment()
        return _publish(rates[0], args.seconds, args.batch)
    probe(rates, args.batch, args.seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
