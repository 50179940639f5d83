"""ROS 2 message type names and their ``.msg`` definitions, as text (no message package is
imported): the one parser of 'pkg/msg/Name' / 'pkg/Name' (``split_type_name``; the rclpy class
of a name is ``hammer_ros.ros.message_types.message_class``, built on it) and the ``ros2msg``
schema text an MCAP file stores beside its messages (``message_definition``), read from the
``.msg`` files shipped in ``hammer_ros/data/ros2_msgs`` or installed under ``sys.prefix/share``."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from ..errors import UsageError
from .cdr import definition_fields, element_type

INPUT_PACKAGES = ("std_msgs", "sensor_msgs", "geometry_msgs")  # the packages of the node's input messages
SCHEMA_DIR = Path(__file__).resolve().parents[1] / "data" / "ros2_msgs"
SCHEMA_SEPARATOR = "=" * 80
_TYPE_NAME = re.compile(r"^([a-z][a-z0-9_]*)/(?:msg/)?([A-Z][A-Za-z0-9]*)$")


def split_type_name(type_name: str | None, packages: tuple[str, ...] | None = None) -> tuple[str, str]:
    """(package, name) of 'pkg/msg/Name' or 'pkg/Name' (from one of ``packages`` when given);
    UsageError naming the type otherwise."""
    match = _TYPE_NAME.match(type_name or "")
    if not match:
        raise UsageError(f"message type {type_name!r}: expected package/msg/Name, e.g. std_msgs/msg/Float64")
    package, name = match.groups()
    if packages is not None and package not in packages:
        raise UsageError(f"message type {type_name!r}: package {package!r} not supported "
                         f"(use one of {', '.join(packages)})")
    return package, name


def normal_type(name: str | None) -> str:
    """'pkg/msg/Name' and 'pkg/Name' compare equal (as 'pkg/Name'); '' for no name."""
    if not name:
        return ""
    parts = name.split("/")
    return f"{parts[0]}/{parts[-1]}"


def message_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of a type: its .msg text followed by every nested type's,
    each after a line of 80 '=' and ``MSG: pkg/Name`` (the layout rosbag2 writes)."""
    package, name = split_type_name(type_name)
    parts, seen, order = {}, set(), []

    def visit(pkg: str, msg: str) -> None:
        key = f"{pkg}/{msg}"
        if key in seen:
            return
        seen.add(key)
        text = msg_text(pkg, msg)
        parts[key] = text
        order.append(key)
        for dep_pkg, dep_msg in _dependencies(text, pkg):
            visit(dep_pkg, dep_msg)

    visit(package, name)
    text = parts[order[0]]
    for key in order[1:]:
        text += f"\n{SCHEMA_SEPARATOR}\nMSG: {key}\n{parts[key]}"
    return text


def msg_text(package: str, name: str) -> str:
    """The ``.msg`` text of ``package/msg/name`` (shipped copy first, then the installed one)."""
    for root in (SCHEMA_DIR, Path(sys.prefix) / "share"):
        file = root / package / "msg" / f"{name}.msg"
        if file.is_file():
            return file.read_text()
    raise UsageError(f"message type {package}/msg/{name}: no .msg definition found")


def _dependencies(text: str, package: str) -> list[tuple[str, str]]:
    """The nested message types of a .msg text, as (package, name) (``cdr.definition_fields``:
    constants and primitive fields are skipped, a bare ``Name`` is in the same package)."""
    bases = [element_type(t) for t in definition_fields(text, package).values()]
    return [(base.split("/")[0], base.split("/")[-1]) for base in bases if "/" in base]
