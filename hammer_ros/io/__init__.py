"""Files: MCAP / rosbag2 bags (``bags``: read a topic's field into a record, write results) and
CSV / NPZ records (``records``).
May import: numpy, yaml, mcap, mcap_ros2, ``hammer_ros.streaming`` (the bag reader aligns with the
engine's aligner), the pure message helpers of ``hammer_ros.ros`` (``field_path``). Never rclpy.
"""
