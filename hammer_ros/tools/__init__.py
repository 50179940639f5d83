"""The tools around the product: ``bench`` (speed and accuracy), ``reproduce`` (the papers'
examples beside their published numbers), ``demo`` (the main job: a simulated plant and the node
on DDS), ``ros_rate_probe`` (the bench's node-throughput measurement), ``processes`` (start and stop
ROS child processes: the demo and the tests) and ``process_status``.
``demo`` and ``ros_rate_probe`` start ROS nodes and import rclpy; the rest does not.
May import every layer, ``cli`` included (``bench`` runs ``replay`` as the command line does);
nothing but ``cli`` (by name, when a subcommand runs) imports the tools.
"""
