"""Files: bags in, MCAP out, and CSV / NPZ records.

Bags (``.mcap`` files and rosbag2 directories): ``bag_config`` (the msg_config YAML, stream specs,
channels), ``bag_index`` (a bag's files, schemas, channels and counts; the fault-tolerant MCAP
scan; warnings), ``bag_reader`` (decoding and aligning samples into a record), ``bag_writer``
(``ResultWriter``, ``JsonWriter``), ``rosbag2`` (a bag's files, storage and zstd compression),
``rosbag2_sqlite`` (``.db3`` files) and ``bags`` (today's import path of all of these, a facade).
``records`` (CSV / NPZ records), ``resample`` (irregular stamps onto a grid), ``replay`` (a bag
through the streaming engine into result messages: the loop of ``hammer-ros replay`` and of each
``hammer-ros fleet`` task) and ``outcome_messages`` (the messages of one solve, as replay writes and
the node publishes them).
May import: numpy, yaml, mcap, mcap_ros2, zstandard, sqlite3, ``hammer_ros.messages`` (field
paths, CDR, the result messages and their ``.msg`` definitions), ``streaming``, ``diagnosis``,
``identification``, ``errors``. Never rclpy, ``ros``, ``fleet``, ``cli`` or ``tools``.
"""

__all__ = [
    "bag_config", "bag_index", "bag_reader", "bag_writer", "bags", "records", "replay", "resample", "rosbag2",
    "rosbag2_sqlite",
]
