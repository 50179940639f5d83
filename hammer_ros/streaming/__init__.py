"""The streaming engine (pure numpy): the live node and bag replay are thin adapters over it.

``config`` (parameters, counters, limits), ``aligner`` (screening, alignment on one grid, gaps),
``correlation_window`` (the recursive correlation sums of the sliding window), ``engine``
(``StreamingEngine`` and ``solve_snapshot``, the periodic solves), ``solver_process`` (solves and
diagnoses in worker processes) and ``sample_clock`` (sample stamps for messages without one).
May import: numpy, scipy, ``hammer_ros.identification``, ``hammer_ros.diagnosis`` (a window's
diagnosis, ``solver_process``), ``hammer_ros.errors``. Never rclpy, ``messages``, ``io`` or above.
"""

__all__ = ["aligner", "config", "correlation_window", "engine", "reference", "sample_clock", "solver_process"]
