"""The ROS 2 edge: everything that imports rclpy or ROS message packages.

``node`` (the live identification node, console script ``hammer_ros_node``; what it is made of
``node_core`` (threads and locks in its docstring), its ``channels`` of ``channel`` each, their
``ingest`` and ``inputs``, its ``parameters``, the lifecycle variant ``managed_node``, its Trigger
services ``services``),
``foxglove_server`` (its in-process Foxglove server), ``dashboard`` (the Foxglove channels as
plain JSON, also written by ``replay --out``), ``plant_node``
(the simulated plant of the demo and the tests), ``live_publisher`` (``replay --rate``),
``environment`` (ROS environment, DDS profile, domain leases), ``cdr`` (raw CDR field reads),
``field_path`` (``/topic:field.path`` specs), ``sample_clock`` (arrival stamps),
``outputs`` (the output messages as plain dicts).
Only the node's modules (``node``, ``node_core``, ``managed_node``, ``channels``, ``channel``,
``ingest``, ``inputs``, ``parameters``, ``services``), ``plant_node`` and ``live_publisher`` import
rclpy at import time (``foxglove_server`` the Foxglove SDK when started); ``cdr`` and
``outputs`` import message packages when asked for a message class; ``dashboard``, ``field_path``,
``sample_clock`` and ``environment`` are pure Python, so files and replay can use them without
rclpy. May import every other layer except ``cli`` and ``tools``.
"""
