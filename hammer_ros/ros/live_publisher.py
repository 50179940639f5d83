"""``replay --rate``: the results of a bag replay published on the live ROS 2 graph."""

from __future__ import annotations

from .environment import prepare_ros_environment

prepare_ros_environment()

import rclpy  # noqa: E402  (the environment must be prepared first)
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from .message_types import message_class, to_ros_message  # noqa: E402


class LivePublisher:
    """Publishes result dicts on the live ROS 2 graph."""

    def __init__(self, node_name: str) -> None:
        self._rclpy = rclpy
        rclpy.init(args=None)
        self.node = rclpy.create_node(node_name)
        self._latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._publishers: dict[str, object] = {}

    def publish(self, topic: str, type_name: str, message: dict) -> None:
        if not self._rclpy.ok():  # SIGINT/SIGTERM shut the context down: stop like Ctrl-C (exit 130)
            raise KeyboardInterrupt
        publisher = self._publishers.get(topic)
        if publisher is None:
            qos = self._latched if topic == "~/model" else 10
            publisher = self._publishers[topic] = self.node.create_publisher(message_class(type_name), topic, qos)
        publisher.publish(to_ros_message(type_name, message))

    def ok(self) -> bool:
        return bool(self._rclpy.ok())

    def close(self) -> None:
        self.node.destroy_node()
        if self._rclpy.ok():
            self._rclpy.shutdown()
