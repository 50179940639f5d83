"""hammer_ros: online identification of Hammerstein systems for ROS 2.

The numerical core (every module except ``node``, ``plant_node``, ``ros_*``, ``demo``
and the CLI/bag adapters) imports only numpy/scipy and never rclpy.
"""

import os

# The regressions here are small (10^3-10^5 x 10-100): BLAS threads only add contention,
# measured 100x slower solves on a loaded 2-core machine. Takes effect when hammer_ros is
# imported before numpy (CLI, node); the user's own setting always wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
