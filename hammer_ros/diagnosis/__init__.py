"""Diagnosis: what a Hammerstein model's simulation gets wrong, why, and the extended model
that accounts for it (``hammer-ros diagnose``, the node's ``~/diagnosis``).
May import: numpy, scipy, ``hammer_ros.identification``, ``hammer_ros.errors``; ``report`` also
matplotlib. Never rclpy.
"""
