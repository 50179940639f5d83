"""A simulated Hammerstein plant on the live ROS 2 graph (the demo's and the tests' robot).

    u(k) = excitation (white Gaussian or uniform),   y(k) = G(q) F[u(k)] (+ white noise)

F is a dead zone or a saturation (``static_maps.PiecewiseLinearMap``), G the resonant
third-order block ``DEMO_PLANT`` (relative degree 2). Samples are produced at ``rate`` Hz of
wall time and published on ``command_topic`` (u) and ``response_topic`` (y) as
std_msgs/Float64 (``batch`` = 1), std_msgs/Float64MultiArray batches of ``batch`` samples (the
last sample of a batch is the newest), or sensor_msgs/JointState (``message_type:=joint_state``,
one sample in position[0], header stamp = sample time). The truth (poles, zeros, a, b, F) is
printed once as ``TRUTH {json}`` on stdout and published on ``truth_topic`` (std_msgs/String,
reliable + transient local).

Run: ``python -m hammer_ros.ros.plant_node --ros-args -p rate:=250.0 -p nonlinearity:=saturation``.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from .environment import prepare_ros_environment

prepare_ros_environment()

import rclpy  # noqa: E402  (the environment must be prepared first)
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor  # noqa: E402
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.experimental import EventsExecutor  # noqa: E402
from rclpy.impl.implementation_singleton import rclpy_implementation  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64, Float64MultiArray, String  # noqa: E402

from ..identification.excitation import gaussian_white_noise, uniform_white_noise  # noqa: E402
from ..identification.linear import LinearModel  # noqa: E402
from ..identification.simulate import HammersteinStream  # noqa: E402
from ..identification.static_maps import PiecewiseLinearMap  # noqa: E402

# resonant pair 0.6 +- 0.6j (|p| = 0.85, 0.785 rad/sample) and a real pole 0.8; one zero (d = 2)
DEMO_PLANT = LinearModel.from_zeros_poles([0.4], [0.8, 0.6 + 0.6j, 0.6 - 0.6j], dc_gain=1.0)
NONLINEARITIES = ("dead_zone", "saturation")
MESSAGE_TYPES = ("float64", "joint_state")
MAX_CATCH_UP_SECONDS = 1.0  # a longer stall of the plant's own timer is a pause, not a burst


def static_map(kind: str, threshold: float) -> PiecewiseLinearMap:
    """Dead zone of half-width ``threshold`` (slope 1 outside) or saturation at +-``threshold``."""
    if kind == "dead_zone":
        return PiecewiseLinearMap([-threshold, threshold], [0.0, 0.0], 1.0, 1.0)
    return PiecewiseLinearMap([-threshold, threshold], [-threshold, threshold], 0.0, 0.0)


def truth_document(linear: LinearModel, nonlinearity: PiecewiseLinearMap, rate: float, amplitude: float) -> dict:
    """The plant's true model in the keys of ``identify --json`` (plus ``rate`` and ``delay``)."""
    def roots(rs):
        return [[float(r.real), float(r.imag)] for r in rs]

    return {"order": linear.order, "delay": linear.delay, "rate": rate,
            "poles": roots(linear.poles), "zeros": roots(linear.zeros), "gain": linear.dc_gain,
            "a": linear.a[1:].tolist(), "b": linear.b.tolist(),
            "nonlinearity": nonlinearity.to_json((-8 * amplitude, 8 * amplitude))}


def _describe(text: str, **ranges) -> ParameterDescriptor:
    return ParameterDescriptor(description=text, read_only=True, **ranges)


class PlantNode(Node):
    """Publishes u and y of the simulated plant at ``rate`` Hz (parameters are read-only)."""

    def __init__(self) -> None:
        super().__init__("plant")
        p = self.declare_parameter
        rate = p("rate", 250.0, _describe("samples per second", floating_point_range=[
            FloatingPointRange(from_value=1.0, to_value=100000.0)])).value
        batch = p("batch", 1, _describe("samples per message (1 = Float64, >1 = Float64MultiArray)",
                                        integer_range=[IntegerRange(from_value=1, to_value=100000)])).value
        kind = p("nonlinearity", "dead_zone", _describe("dead_zone or saturation")).value
        threshold = p("threshold", 0.2, _describe("dead-zone half-width / saturation level", floating_point_range=[
            FloatingPointRange(from_value=0.0, to_value=1e6)])).value
        excitation = p("excitation", "gaussian", _describe("gaussian (std = amplitude) or uniform (+-amplitude)")).value
        self.amplitude = p("amplitude", 0.5, _describe("excitation std / half-range")).value
        noise = p("noise", 0.0, _describe("std of white noise added to y")).value
        seed = p("seed", 1, _describe("random seed")).value
        message_type = p("message_type", "float64", _describe("float64 (std_msgs) or joint_state (stamped)")).value
        command_topic = p("command_topic", "/command", _describe("topic of u")).value
        response_topic = p("response_topic", "/response", _describe("topic of y")).value
        truth_topic = p("truth_topic", "/plant/truth", _describe("topic of the true model (JSON)")).value
        for name, value, allowed in (("nonlinearity", kind, NONLINEARITIES), ("excitation", excitation,
                                     ("gaussian", "uniform")), ("message_type", message_type, MESSAGE_TYPES)):
            if value not in allowed:
                raise SystemExit(f"plant: parameter {name}: {value!r} is not one of {', '.join(allowed)}")
        if message_type == "joint_state" and batch != 1:
            raise SystemExit("plant: parameter batch: joint_state messages carry one sample (batch must be 1)")

        self.rate, self.batch, self.message_type, self.noise = rate, batch, message_type, noise
        self.excitation = gaussian_white_noise if excitation == "gaussian" else uniform_white_noise
        self.rng = np.random.default_rng(seed)
        nonlinearity = static_map(kind, threshold)
        self.plant = HammersteinStream(nonlinearity, DEMO_PLANT)
        self.truth = truth_document(DEMO_PLANT, nonlinearity, rate, self.amplitude)

        msg_type = {"float64": Float64 if batch == 1 else Float64MultiArray, "joint_state": JointState}[message_type]
        self.command_pub = self.create_publisher(msg_type, command_topic, 1000)
        self.response_pub = self.create_publisher(msg_type, response_topic, 1000)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_publisher(String, truth_topic, latched).publish(String(data=json.dumps(self.truth)))
        print("TRUTH " + json.dumps(self.truth), flush=True)

        self.produced = 0
        self.start = time.monotonic()
        self.stamp_origin = self.get_clock().now().nanoseconds * 1e-9
        self.create_timer(max(batch / rate, 0.002), self._tick)

    def _samples(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        if self.excitation is gaussian_white_noise:
            u = gaussian_white_noise(n, self.amplitude, seed=self.rng)
        else:
            u = uniform_white_noise(n, -self.amplitude, self.amplitude, seed=self.rng)
        y = self.plant(u)
        if self.noise > 0:
            y = y + self.noise * self.rng.standard_normal(n)
        return u, y

    def _tick(self) -> None:
        due = int((time.monotonic() - self.start) * self.rate) - self.produced
        if due > MAX_CATCH_UP_SECONDS * self.rate:  # the plant itself was stalled: resume from now
            self.produced += due - self.batch
            due = self.batch
        messages = due // self.batch
        if messages <= 0:
            return
        u, y = self._samples(messages * self.batch)
        first = self.produced
        self.produced += messages * self.batch
        for m in range(messages):
            chunk = slice(m * self.batch, (m + 1) * self.batch)
            if self.message_type == "joint_state":
                self._publish_joint_state(first + m, float(u[m]), float(y[m]))
            elif self.batch == 1:
                self.command_pub.publish(Float64(data=float(u[m])))
                self.response_pub.publish(Float64(data=float(y[m])))
            else:
                self.command_pub.publish(Float64MultiArray(data=u[chunk].tolist()))
                self.response_pub.publish(Float64MultiArray(data=y[chunk].tolist()))

    def _publish_joint_state(self, index: int, u: float, y: float) -> None:
        ns = int(round((self.stamp_origin + index / self.rate) * 1e9))
        for pub, value in ((self.command_pub, u), (self.response_pub, y)):
            msg = JointState(name=["joint"], position=[value])
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
            pub.publish(msg)


def main(argv: list[str] | None = None) -> int:
    rclpy.init(args=sys.argv if argv is None else ["plant_node", *argv])
    node = None
    try:
        node = PlantNode()
        executor = EventsExecutor()
        executor.add_node(node)
        while rclpy.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except rclpy_implementation.RCLError:
                if rclpy.ok():
                    raise
                break  # Ctrl-C shut the context down in the middle of a timer's publish: a clean stop
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
