"""The ROS 2 edge: everything that imports rclpy or ROS message packages.

``node`` (the live identification node, console script ``hammer_ros_node``), ``plant_node``
(the simulated plant of the demo and the tests), ``live_publisher`` (``replay --rate``),
``environment`` (ROS environment, DDS profile, domain leases), ``cdr`` (raw CDR field reads),
``field_path`` (``/topic:field.path`` specs), ``sample_clock`` (arrival stamps),
``outputs`` (the output messages as plain dicts).
Only ``node``, ``plant_node`` and ``live_publisher`` import rclpy at import time; ``cdr`` and
``outputs`` import message packages when asked for a message class; ``field_path``,
``sample_clock`` and ``environment`` are pure Python, so files and replay can use them without
rclpy. May import every other layer except ``cli`` and ``tools``.
"""
