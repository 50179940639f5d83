"""hammer_ros: online identification of Hammerstein systems for ROS 2.

Layers, bottom to top, each a subpackage whose docstring says what it may import (only layers
below it; ``test/test_layout.py`` holds the allowlists):

- ``errors``, ``process_status``: the base modules;
- ``identification``: the papers' methods and the linear/static-map/regression pieces (numpy/scipy);
- ``diagnosis``: what the model gets wrong, why, and the extended model;
- ``streaming``: the streaming engine (numpy);
- ``messages``: the ROS 2 message format as data (field paths, CDR, result messages, dashboard);
- ``io``: MCAP/rosbag2 bags, CSV/NPZ records, replay;
- ``reproduce`` (the papers' examples), ``fleet`` (many bags on Dask);
- ``ros``: everything that imports rclpy or ROS message packages (the node, message classes);
- ``cli``: the ``hammer-ros`` command line;
- ``tools``: bench, demo, rate probe;
- ``api``: the Python API, re-exported here (``hammer_ros.identify``, ``diagnose``, ``read``, ``Model``,
  ``Diagnosis``, ``Record``), imported on first use so that ``import hammer_ros`` stays light.

Nothing outside ``ros`` imports rclpy: ``pip install .`` without the ``ros`` extra gives the
core, ``identify``, ``diagnose``, ``reproduce`` and ``replay``.
"""

import os

# The regressions here are small (10^3-10^5 x 10-100): BLAS threads only add contention,
# measured 100x slower solves on a loaded 2-core machine. Takes effect when hammer_ros is
# imported before numpy (CLI, node); the user's own setting always wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

__version__ = "0.1.0"

__all__ = ["Diagnosis", "Model", "Record", "diagnose", "identify", "read"]


def __getattr__(name: str):
    """The API's names (``hammer_ros.api``), imported when first asked for."""
    if name in __all__:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'hammer_ros' has no attribute {name!r}")
