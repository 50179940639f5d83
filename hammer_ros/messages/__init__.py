"""The ROS 2 message format, as data: field paths into messages (``field_path``), raw CDR reads
(``cdr``), type names and ``.msg`` definitions (``types``), the result messages as plain dicts
(``outputs``) and the Foxglove dashboard channels built from them (``dashboard``).
May import: numpy, ``hammer_ros.errors``, ``identification``, ``streaming``. Never rclpy nor a ROS
message package (``hammer_ros.ros.message_types`` binds these to the installed classes), nor
``io``, ``ros``, ``fleet``, ``cli``, ``tools``.
"""

__all__ = ["cdr", "dashboard", "field_path", "outputs", "types"]
