"""ROS 2 message type names and their ``.msg`` definitions, as text (no message package is
imported): the one parser of 'pkg/msg/Name' / 'pkg/Name' (``split_type_name``; the rclpy class
of a name is ``hammer_ros.ros.message_types.message_class``, built on it) and the ``ros2msg``
schema text an MCAP file stores beside its messages (``message_definition``), read from the
``.msg`` files shipped in ``hammer_ros/data/ros2_msgs`` or installed under ``sys.prefix/share``;
and that text parsed into field name -> IDL type tables (``definition_fields``, ``schema_fields``:
the layout ``cdr`` reads a bag's messages by)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from ..errors import UsageError

INPUT_PACKAGES = ("std_msgs", "sensor_msgs", "geometry_msgs")  # the packages of the node's input messages
SCHEMA_DIR = Path(__file__).resolve().parents[1] / "data" / "ros2_msgs"
SCHEMA_SEPARATOR = "=" * 80
_TYPE_NAME = re.compile(r"^([a-z][a-z0-9_]*)/(?:msg/)?([A-Z][A-Za-z0-9]*)$")
SEQUENCE_TYPE = re.compile(r"^sequence<([^,>]+)(?:,\s*\d+)?>$")
ARRAY_TYPE = re.compile(r"^(.+)\[(\d+)\]$")
MSG_TO_IDL = {"float64": "double", "float32": "float", "bool": "boolean", "byte": "octet", "char": "uint8",
              **{t: t for t in ("int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
                                "string", "wstring")}}
_MSG_FIELD = re.compile(r"^([A-Za-z0-9_/]+)(?:<=(\d+))?(?:\[(<=)?(\d*)\])?$")


class UnsupportedLayout(Exception):
    """A field or a ``.msg`` line that ``cdr`` cannot lay out (the caller falls back to messages)."""


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
    """The nested message types of a .msg text, as (package, name) (``definition_fields``:
    constants and primitive fields are skipped, a bare ``Name`` is in the same package)."""
    bases = [element_type(t) for t in definition_fields(text, package).values()]
    return [(base.split("/")[0], base.split("/")[-1]) for base in bases if "/" in base]


def definition_fields(text: str, package: str) -> dict[str, str]:
    """Field name -> IDL type of one ``.msg`` definition (the form of
    ``get_fields_and_field_types``): ``float64[]`` -> ``sequence<double>``, ``float64[<=3]`` ->
    ``sequence<double, 3>``, ``float64[9]`` -> ``double[9]``, ``string<=8`` -> ``string<8>``,
    ``Header`` -> ``std_msgs/Header``, a bare ``Name`` -> ``package/Name``; constants
    (``uint8 OK=0``) are left out. Raises UnsupportedLayout on a line it cannot read."""
    fields = {}
    for line in text.splitlines():
        tokens = line.split("#", 1)[0].split(None, 1)
        if not tokens:
            continue
        rest = tokens[1].strip() if len(tokens) > 1 else ""
        name = re.match(r"^([A-Za-z_][A-Za-z0-9_]*)\s*(=)?", rest)
        match = _MSG_FIELD.match(tokens[0])
        if name is None or match is None:
            raise UnsupportedLayout(line.strip())
        if name.group(2):  # a constant
            continue
        base, bound, upper, size = match.groups()
        if base in MSG_TO_IDL:
            idl = MSG_TO_IDL[base] + (f"<{bound}>" if bound else "")
        elif base == "Header":
            idl = "std_msgs/Header"
        else:
            pkg, _, msg = base.rpartition("/")
            idl = f"{pkg.split('/')[0] if pkg else package}/{msg}"
        if match.group(0).endswith("]"):
            idl = f"{idl}[{size}]" if size and not upper else f"sequence<{idl}{', ' + size if upper else ''}>"
        fields[name.group(1)] = idl
    return fields


def schema_fields(name: str, text: str) -> dict[str, dict[str, str]]:
    """'pkg/Name' -> fields (``definition_fields``) of every type in a ``ros2msg`` schema: the
    named type's definition, then each nested type's after a line of '=' and ``MSG: pkg/Name``."""
    sections = re.split(r"^=+\s*$", text, flags=re.MULTILINE)
    types = {}
    for i, section in enumerate(sections):
        if i == 0:
            type_name, body = name, section
        else:
            header = re.match(r"\s*MSG:\s*(\S+)\s*\n?", section)
            if header is None:
                raise UnsupportedLayout(f"schema {name}: a section without 'MSG: pkg/Name'")
            type_name, body = header.group(1), section[header.end():]
        parts = type_name.split("/")
        types[f"{parts[0]}/{parts[-1]}"] = definition_fields(body, parts[0])
    return types


def element_type(type_name: str) -> str:
    """The element type of an IDL type: ``sequence<T>``, ``sequence<T, N>`` and ``T[N]`` -> T."""
    match = SEQUENCE_TYPE.match(type_name) or ARRAY_TYPE.match(type_name)
    return match.group(1).strip() if match else type_name
