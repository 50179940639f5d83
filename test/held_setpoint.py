"""A position servo driven by a held setpoint, recorded as a robot records it: the setpoint on
/setpoint (sensor_msgs/JointState, position[0]) at 1 Hz with every header stamp ZERO, the
servo's position on /joint_states (JointState, position[0]) at 100 Hz with header stamp = sample
time (log time 0.5 ms later). The servo: a continuous second-order loop (natural frequency
``OMEGA``, damping ``ZETA``, static gain 1) under the zero-order-held setpoint, discretised at
100 Hz; the setpoint is a staircase of random levels, one a second.

``python -m held_setpoint BAG [RATE]`` plays the bag's two topics as recorded (their CDR bytes,
header stamps untouched) at RATE x speed once the node's two subscriptions are matched, then
exits: the live test's publisher process."""

from __future__ import annotations

import contextlib
import os
import signal as signals
import sys
import time
from pathlib import Path

import numpy as np
from scipy import signal

STATE_RATE = 100.0
OMEGA, ZETA = 2 * np.pi * 0.7, 0.6
START_NS = 1_700_000_000_000_000_000  # a recording's epoch time
TOPICS = {"setpoint": "/setpoint", "state": "/joint_states"}
CONFIG = """hammer_ros:
  ros__parameters:
    excitation_topic: /setpoint
    excitation_type: sensor_msgs/msg/JointState
    excitation_field: position[0]
    response_topic: /joint_states
    response_type: sensor_msgs/msg/JointState
    response_field: position[0]
"""


def pole(rate: float) -> complex:
    """The servo's pole of positive imaginary part, sampled at ``rate`` Hz: exp(s / rate)."""
    return complex(np.exp(complex(-ZETA * OMEGA, OMEGA * np.sqrt(1 - ZETA**2)) / rate))


def servo(seconds: float, seed: int = 3, levels: np.ndarray | None = None, rate: float = STATE_RATE,
          noise: float = 0.002) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(setpoint levels, one a second, held from second j; state at ``rate``; the setpoint as
    the servo saw it at each state sample). The state is the discretised loop's response (ZOH,
    so the position at sample k depends on the setpoint up to sample k - 1) plus ``noise``
    (sd, rad). Random levels start from zero state; given ``levels`` start at rest at the first
    one, as a robot's joint held at its first set point does."""
    rng = np.random.default_rng(seed)
    at_rest = levels is not None
    levels = rng.uniform(-1.0, 1.0, int(seconds)) if levels is None else np.asarray(levels, dtype=float)
    held = np.repeat(levels, int(rate))
    num, den, _ = signal.cont2discrete(([OMEGA**2], [1.0, 2 * ZETA * OMEGA, OMEGA**2]), 1 / rate)
    num = np.ravel(num)
    zi = signal.lfilter_zi(num, den) * held[0] if at_rest else np.zeros(den.size - 1)
    state = signal.lfilter(num, den, held, zi=zi)[0]
    return levels, state + noise * rng.standard_normal(held.size), held


def write_bag(path, seconds: float = 40.0, silence: tuple[float, float] | None = None, seed: int = 3,
              levels: np.ndarray | None = None, rate: float = STATE_RATE, sqlite: bool = False) -> np.ndarray:
    """The recording as a rosbag2 directory (MCAP storage, or SQLite as ``ros2 bag record`` wrote
    it before Iron, written by rosbags); ``silence``: (start, length) s in which /joint_states
    publishes nothing; ``levels``, ``rate``: as ``servo``. Returns the state samples."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    levels, state, _ = servo(seconds, seed, levels, rate)
    period_ns = int(1e9 / rate)

    def joint_state(value: float, stamp_ns: int) -> bytes:
        stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        msg = types["sensor_msgs/msg/JointState"](
            header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=""), name=["joint"],
            position=np.array([value]), velocity=np.array([], dtype=float), effort=np.array([], dtype=float))
        return store.serialize_cdr(msg, "sensor_msgs/msg/JointState")

    with Writer(path, version=8, storage_plugin=StoragePlugin.SQLITE3 if sqlite else StoragePlugin.MCAP) as writer:
        setpoint = writer.add_connection(TOPICS["setpoint"], "sensor_msgs/msg/JointState", typestore=store)
        joints = writer.add_connection(TOPICS["state"], "sensor_msgs/msg/JointState", typestore=store)
        per_level = int(rate)
        for k, y in enumerate(state):
            t = START_NS + k * period_ns
            if k % per_level == 0:
                writer.write(setpoint, t, joint_state(float(levels[k // per_level]), 0))
            if silence is None or not silence[0] <= k / rate < silence[0] + silence[1]:
                writer.write(joints, t + 500_000, joint_state(float(y), t))
    return state


@contextlib.contextmanager
def played_into_node(bag, node_parameters: str, ros_env: dict, tmp_path, rate: float = 2.0):
    """``hammer_ros.ros.node`` started from a params file (CONFIG and ``node_parameters``), the bag's
    two topics played into it at ``rate`` x by a player process (``play``); yields (the node, a
    listener, the ~/model documents, the /diagnostics values) and stops both processes after."""
    from ros_helpers import Listener, RosProcess

    params = tmp_path / "params.yaml"
    params.write_text(CONFIG + node_parameters)
    env = {**ros_env, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), ros_env.get("PYTHONPATH", "")])}
    node = RosProcess("hammer_ros.ros.node", {}, env, tmp_path / "node.log",
                      options=("--ros-args", "--params-file", str(params)))
    listener = Listener(env)
    player = None
    try:
        models = listener.subscribe_json("/hammer_ros/model")
        diagnostics = listener.subscribe_diagnostics()
        player = RosProcess("held_setpoint", {}, env, tmp_path / "player.log", options=(str(bag), str(rate)))
        yield node, listener, models, diagnostics
    finally:
        listener.close()
        if player is not None:
            player.stop(signals.SIGINT)
        assert node.stop(signals.SIGINT) == 0, node.output()[-3000:]


def model_on(listener, models: list, samples: int = 500) -> dict:
    """The first ~/model that is not stale and holds at least ``samples`` samples in its window."""
    return listener.wait_for(lambda: next((m for m in models if m["samples"] >= samples and not m.get("stale")),
                                          None), timeout=90.0, what=f"a model on >= {samples} samples")


def play(bag: str, rate: float) -> None:
    """Publish the bag's two topics (serialized, as recorded) at ``rate`` x speed."""
    import rclpy
    from rosbags.rosbag2 import Reader
    from sensor_msgs.msg import JointState

    rclpy.init()
    node = rclpy.create_node("held_setpoint_player")
    publishers = {topic: node.create_publisher(JointState, topic, 100) for topic in TOPICS.values()}
    deadline = time.monotonic() + 60.0
    while not all(p.get_subscription_count() for p in publishers.values()):  # the node's subscriptions
        if time.monotonic() > deadline:
            raise SystemExit("the node never subscribed")
        rclpy.spin_once(node, timeout_sec=0.05)
    with Reader(bag) as reader:
        messages = [(log_time, connection.topic, bytes(data)) for connection, log_time, data in reader.messages()]
    messages.sort(key=lambda m: m[0])
    first, start = messages[0][0], time.monotonic()
    for log_time, topic, data in messages:
        due = start + (log_time - first) * 1e-9 / rate
        while (left := due - time.monotonic()) > 0:  # paced as the recording
            time.sleep(min(left, 0.01))
        publishers[topic].publish(data)
    print(f"played {len(messages)} messages", flush=True)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    play(sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 1.0)
