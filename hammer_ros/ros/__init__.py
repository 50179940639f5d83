"""The ROS 2 edge: everything that imports rclpy or a ROS message package, and nothing else.

``node`` (the live identification node, console script ``hammer_ros_node``; what it is made of:
``node_core`` (threads and locks in its docstring), its ``channels`` of ``channel`` each, their
``ingest`` and ``inputs``, its ``parameters``, the lifecycle variant ``managed_node``, its Trigger
services ``services``, its in-process Foxglove server ``foxglove_server``), ``message_types`` (the
installed message classes behind type names, rclpy messages from result dicts), ``plant_node`` (the
simulated plant of the demo and the tests), ``live_publisher`` (``replay --rate``), ``environment``
(ROS environment, DDS profile, domain leases, set before rclpy is imported), ``demo_watcher`` (the
demo's node) and the rate probe's parts by role: ``rate_probe_publisher``,
``rate_probe_subscriber``, ``rate_probe_node``, ``rate_probe_session``.
The message format as data (field paths, CDR, the result messages, the dashboard channels) is
``hammer_ros.messages``, below ``io``.
May import every other layer except ``fleet``, ``cli`` and ``tools``.
"""

__all__ = [
    "channels", "demo_watcher", "environment", "foxglove_server", "live_publisher", "managed_node",
    "message_types", "node", "node_core", "plant_node", "rate_probe_node", "rate_probe_publisher",
    "rate_probe_session", "rate_probe_subscriber", "services",
]
