"""Files: MCAP / rosbag2 bags (``bags``: read a topic's field into a record, write results),
CSV / NPZ records (``records``) and ``replay`` (a bag through the streaming engine into result
messages: the loop of ``hammer-ros replay`` and of each ``hammer-ros fleet`` task), ``outcome_messages``
(the messages of one solve, as replay writes and the node publishes them).
``rosbag2`` (a bag's files, storage and zstd compression) and ``rosbag2_sqlite`` (``.db3`` files).
May import: numpy, yaml, mcap, mcap_ros2, zstandard, sqlite3, ``hammer_ros.streaming`` (the bag
reader aligns with the engine's aligner), the pure message helpers of ``hammer_ros.ros`` (``field_path``, ``outputs``).
Never rclpy.
"""
