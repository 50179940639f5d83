"""Field paths into ROS 2 messages: ``data``, ``data[0]``, ``velocity[2]``, ``twist.linear.x``,
``data[:]`` (every element: a batch of samples), ``header.stamp``, ``position[shoulder_pan_joint]``.

A bracket that is not an integer nor ``:`` is a *name*: ``position[elbow]`` is the element of
``position`` at the index of ``elbow`` in the sibling ``name`` array of the same message
(sensor_msgs/JointState, whose order no publisher guarantees), looked up in every message. A
message whose ``name`` lacks it raises ``MissingName`` (a FieldError: the message is counted and
skipped, never read at another joint's index). ``position[2]`` stays an index.

Pure Python: works on rclpy message objects, on objects decoded by ``mcap_ros2`` or
``rosbags`` (attribute access) and on plain dicts (item access). Numeric sequences may be
lists, ``array.array`` or numpy arrays.

Batch convention: a message carrying n samples with stamp t (its header stamp, else the
receive / log time) holds samples at t - (n-1)/fs, ..., t - 1/fs, t: the LAST sample is at the
stamp, fs is the configured (or inferred) sample rate. ``StreamingEngine.message_stamps``
applies it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from numbers import Real
from typing import Any

import numpy as np

from ..errors import UsageError


class FieldError(UsageError):
    """A field path that does not exist in a message, or does not hold numbers."""


class MissingName(FieldError):
    """A named element (``position[NAME]``) whose name is not in this message's ``name`` array."""


NAME_FIELD = "name"  # the sibling array a named index is looked up in
_SEGMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[[^\[\]]+\])*)$")
_INDEX = re.compile(r"\[([^\[\]]+)\]")
_INTEGER = re.compile(r"^-?\d+$")


@dataclass(frozen=True)
class FieldStep:
    """One ``name[i][j]`` segment: attribute ``name`` then indices (None = ``[:]``, all elements;
    a str = the element named so in the sibling ``name`` array, only as the first index)."""

    name: str
    indices: tuple[int | str | None, ...] = ()

    @property
    def element_name(self) -> str | None:
        """The name of ``field[NAME]``, None for an index."""
        return self.indices[0] if self.indices and isinstance(self.indices[0], str) else None


@dataclass(frozen=True)
class FieldPath:
    """A parsed field path; ``text`` is the path as the user wrote it."""

    text: str
    steps: tuple[FieldStep, ...]

    @property
    def is_batch(self) -> bool:
        """True when the path selects all elements of a sequence (``[:]``)."""
        return any(i is None for step in self.steps for i in step.indices)

    def __str__(self) -> str:
        return self.text


def _segments(text: str) -> list[str]:
    """``text`` split at the dots outside brackets (a joint name may hold a dot)."""
    segments, depth, start = [], 0, 0
    for i, char in enumerate(text):
        depth += (char == "[") - (char == "]")
        if char == "." and depth == 0:
            segments.append(text[start:i])
            start = i + 1
    return [*segments, text[start:]]


def _parse_index(text: str) -> int | str | None:
    text = text.strip()
    return None if text == ":" else int(text) if _INTEGER.match(text) else text


def parse_field_path(text: str) -> FieldPath:
    """Parse ``a.b[2].c`` / ``data[:]`` / ``position[elbow_joint]``; a malformed path raises
    UsageError naming it."""
    if not isinstance(text, str) or not text.strip():
        raise UsageError("field path: empty (expected e.g. 'data', 'velocity[0]', 'position[elbow_joint]')")
    text = text.strip()
    steps = []
    for segment in _segments(text):
        match = _SEGMENT.match(segment)
        if not match:
            raise UsageError(
                f"field path {text!r}: bad segment {segment!r} (expected name, name[i], name[NAME] or name[:])"
            )
        indices = tuple(_parse_index(i) for i in _INDEX.findall(match.group(2)))
        if sum(i is None for i in indices) > 1:
            raise UsageError(f"field path {text!r}: at most one [:] per segment")
        if any(isinstance(i, str) for i in indices[1:]):
            raise UsageError(f"field path {text!r}: a name ([NAME]) only as the first index of a field")
        steps.append(FieldStep(match.group(1), indices))
    if sum(i is None for s in steps for i in s.indices) > 1:
        raise UsageError(f"field path {text!r}: at most one [:] in a path")
    return FieldPath(text, tuple(steps))


def _attribute(obj: Any, name: str, path: FieldPath) -> Any:
    if isinstance(obj, dict):
        if name in obj:
            return obj[name]
    elif hasattr(obj, name) and not name.startswith("__"):
        return getattr(obj, name)
    fields = _field_names(obj)
    hint = f" (fields: {', '.join(fields)})" if fields else ""
    raise FieldError(f"field {path.text!r}: no field {name!r} in {type(obj).__name__}{hint}")


def _field_names(obj: Any) -> list[str]:
    if isinstance(obj, dict):
        return list(obj)
    slots = getattr(obj, "__slots__", None) or getattr(obj, "__dataclass_fields__", None)
    if slots:
        return [s.lstrip("_") for s in slots]
    return [k for k in vars(obj) if not k.startswith("_")] if hasattr(obj, "__dict__") else []


def _is_sequence(obj: Any) -> bool:
    return isinstance(obj, (list, tuple, np.ndarray)) or type(obj).__name__ == "array"


def _index(obj: Any, index: int | None, path: FieldPath, name: str) -> Any:
    if not _is_sequence(obj):
        raise FieldError(f"field {path.text!r}: {name!r} is not an array ({type(obj).__name__})")
    if index is None:
        return obj
    if not -len(obj) <= index < len(obj):
        raise FieldError(f"field {path.text!r}: index {index} out of range, {name!r} has {len(obj)} elements")
    return obj[index]


def _to_float_array(value: Any, path: FieldPath) -> np.ndarray:
    if hasattr(value, "sec") and hasattr(value, "nanosec"):  # builtin_interfaces/Time or Duration
        return np.array([value.sec + 1e-9 * value.nanosec])
    if isinstance(value, dict) and "sec" in value and "nanosec" in value:
        return np.array([value["sec"] + 1e-9 * value["nanosec"]])
    if isinstance(value, (bool, np.bool_)) or (isinstance(value, Real) and not isinstance(value, bool)):
        return np.array([float(value)])
    if _is_sequence(value):
        try:
            out = np.asarray(value, dtype=float).ravel()
        except (TypeError, ValueError):
            raise FieldError(f"field {path.text!r}: not a numeric array") from None
        return out
    raise FieldError(f"field {path.text!r}: not numeric ({type(value).__name__})")


def named_index(names: Any, element: str, path: FieldPath) -> int:
    """The index of ``element`` in a message's ``name`` array; MissingName when it is not there."""
    if not _is_sequence(names):
        raise FieldError(f"field {path.text!r}: {NAME_FIELD!r} is not an array ({type(names).__name__})")
    try:
        return list(names).index(element)
    except ValueError:
        raise MissingName(f"field {path.text!r}: no {element!r} in this message's {NAME_FIELD} "
                          f"({', '.join(map(str, names)) or 'empty'})") from None


def extract_samples(msg: Any, path: FieldPath) -> np.ndarray:
    """The numbers at ``path`` in ``msg`` as a 1-D float array: one sample for a scalar field,
    every element for ``[:]`` or a numeric array field, the element at a name's index in the
    sibling ``name`` array for ``field[NAME]``. Raises FieldError naming the field."""
    value = msg
    for step in path.steps:
        parent, value = value, _attribute(value, step.name, path)
        for index in step.indices:
            if isinstance(index, str):
                index = named_index(_attribute(parent, NAME_FIELD, path), index, path)
            value = _index(value, index, path, step.name)
    return _to_float_array(value, path)


def message_stamp(msg: Any) -> float | None:
    """header.stamp in seconds when the message has a header, else None."""
    ns = message_stamp_ns(msg)
    return None if ns is None else ns // 1_000_000_000 + 1e-9 * (ns % 1_000_000_000)


def message_stamp_ns(msg: Any) -> int | None:
    """header.stamp in integer nanoseconds when the message has a header, else None."""
    header = msg.get("header") if isinstance(msg, dict) else getattr(msg, "header", None)
    if header is None:
        return None
    stamp = header.get("stamp") if isinstance(header, dict) else getattr(header, "stamp", None)
    if stamp is None:
        return None
    if isinstance(stamp, dict):
        return int(stamp["sec"]) * 1_000_000_000 + int(stamp["nanosec"])
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
