"""The streaming engine (pure numpy): the live node and bag replay are thin adapters over it.

``config`` (parameters, counters, limits), ``aligner`` (screening, alignment on one grid, gaps),
``correlation_window`` (the recursive correlation sums of the sliding window) and ``engine``
(``StreamingEngine`` and ``solve_snapshot``, the periodic solves).
May import: numpy, scipy, ``hammer_ros.identification``, ``hammer_ros.errors``. Never rclpy.
"""
