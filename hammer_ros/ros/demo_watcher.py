"""The watcher of ``hammer-ros demo`` (``hammer_ros.tools.demo``): an rclpy node that keeps the
plant's truth, the identification node's latest model and its status for the demo's table."""

from __future__ import annotations

import json
import time


class DemoWatcher:
    """The demo's own ROS node: the latest truth (/plant/truth), model (/hammer_ros/model) and
    status (/diagnostics), read while ``spin_until`` runs."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.experimental import EventsExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import String

        self.rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node("hammer_ros_demo")
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.truth: dict | None = None
        self.model: dict | None = None
        self.models = 0
        self.status = "starting"
        self.node.create_subscription(String, "/plant/truth", self._on_truth, latched)
        self.node.create_subscription(String, "/hammer_ros/model", self._on_model, latched)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self.executor = EventsExecutor()
        self.executor.add_node(self.node)

    def _on_truth(self, msg) -> None:
        self.truth = json.loads(msg.data)

    def _on_model(self, msg) -> None:
        self.model = json.loads(msg.data)
        self.models += 1

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if status.name.startswith("hammer_ros"):
                self.status = status.message

    def spin_until(self, deadline: float) -> None:
        while self.rclpy.ok() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=max(0.0, min(0.1, deadline - time.monotonic())))

    def close(self) -> None:
        self.node.destroy_node()
        self.rclpy.try_shutdown()
