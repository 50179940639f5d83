"""hammer_ros: online identification of Hammerstein systems for ROS 2.

The numerical core (every module except ``node``, ``plant_node``, ``ros_*``, ``demo``
and the CLI/bag adapters) imports only numpy/scipy and never rclpy.
"""

__version__ = "0.1.0"
