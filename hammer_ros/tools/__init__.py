"""The tools around the product: ``bench`` (speed and accuracy), ``demo`` (the main job: a
simulated plant and the node on DDS), ``ros_rate_probe`` (the bench's node-throughput
measurement), ``closed_loop_study``, ``uncertainty_check``, ``foxglove_layout`` and ``processes`` (start and
stop ROS child processes: the demo and the tests). Their rclpy
parts are in ``hammer_ros.ros`` (``demo_watcher``, ``rate_probe_*``).
The top layer. May import every layer, ``cli`` included (``bench`` runs ``replay`` as the command
line does); no module imports the tools (``cli`` runs ``demo`` and ``bench`` by module name, when
the subcommand runs).
"""

__all__ = ["bench", "closed_loop_study", "demo", "foxglove_layout", "ros_rate_probe", "uncertainty_check"]
