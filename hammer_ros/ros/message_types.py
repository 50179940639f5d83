"""The installed ROS 2 message classes behind type names: the one resolver of the node, its
publishers and ``replay --rate`` (``message_class``; the text of a name is parsed by
``hammer_ros.messages.types.split_type_name``), the fields of nested types for the raw CDR
readers of ``hammer_ros.messages.cdr`` (``raw_extractor``, ``topic_decoder``), and result dicts of
``hammer_ros.messages.outputs`` as rclpy message objects (``to_ros_message``). Imports message
packages (``std_msgs.msg``, ...) when asked for a class."""

from __future__ import annotations

from importlib import import_module

import numpy as np

from ..errors import UsageError
from ..messages import cdr
from ..messages.field_path import FieldPath
from ..messages.types import INPUT_PACKAGES, split_type_name


def message_class(type_name: str, packages: tuple[str, ...] | None = None):
    """The rclpy message class of 'pkg/msg/Name' (or 'pkg/Name'), from one of ``packages`` when
    given; UsageError naming the type when there is none."""
    package, name = split_type_name(type_name, packages)
    try:
        cls = getattr(import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        raise UsageError(f"message type {type_name!r}: no such message in {package}") from None
    if not hasattr(cls, "get_fields_and_field_types"):
        raise UsageError(f"message type {type_name!r}: not a message")
    return cls


def input_message_class(type_name: str):
    """``message_class`` of a node input (``excitation_type``, ...): one of ``INPUT_PACKAGES``."""
    return message_class(type_name, INPUT_PACKAGES)


def installed_fields(type_name: str) -> dict[str, str]:
    """Field name -> IDL type of an installed message type 'pkg/Name' (or 'pkg/msg/Name');
    ImportError when there is none (the raw readers then fall back to rclpy's messages)."""
    try:
        return message_class(type_name).get_fields_and_field_types()
    except UsageError as exc:
        raise ImportError(str(exc)) from None


def raw_extractor(cls, path: FieldPath) -> cdr.Extract | None:
    """``cdr.raw_extractor`` for messages of the installed class ``cls``."""
    return cdr.raw_extractor(cls, path, installed_fields)


def topic_decoder(cls, paths: list[FieldPath]) -> cdr.TopicDecoder | None:
    """``cdr.topic_decoder`` for messages of the installed class ``cls``."""
    return cdr.topic_decoder(cls, paths, installed_fields)


def to_ros_message(type_name: str, values: dict):
    """An rclpy message object of ``type_name`` filled from a nested dict of ``messages.outputs``."""
    return _fill(message_class(type_name)(), values)


def _fill(msg, values: dict):
    types = msg.get_fields_and_field_types()
    for key, value in values.items():
        field_type = types[key]
        if isinstance(value, dict):
            _fill(getattr(msg, key), value)
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            element = field_type[field_type.index("<") + 1 : field_type.rindex(">")]
            cls = message_class(element)
            setattr(msg, key, [_fill(cls(), v) for v in value])
        elif field_type in ("byte", "octet"):  # rclpy names the byte type "octet"
            setattr(msg, key, bytes([int(value)]))
        elif field_type in ("float", "double") or field_type.startswith(("sequence<double", "sequence<float")):
            setattr(msg, key, np.asarray(value, dtype=float).tolist() if isinstance(value, list) else float(value))
        else:
            setattr(msg, key, value)
    return msg
