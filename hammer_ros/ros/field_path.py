"""Field paths into ROS 2 messages: ``data``, ``data[0]``, ``velocity[2]``, ``twist.linear.x``,
``data[:]`` (every element: a batch of samples), ``header.stamp``.

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


_SEGMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[(?:-?\d+|:)\])*)$")
_INDEX = re.compile(r"\[(-?\d+|:)\]")


@dataclass(frozen=True)
class FieldStep:
    """One ``name[i][j]`` segment: attribute ``name`` then indices (None = ``[:]``, all elements)."""

    name: str
    indices: tuple[int | None, ...] = ()


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


def parse_field_path(text: str) -> FieldPath:
    """Parse ``a.b[2].c`` / ``data[:]``; a malformed path raises UsageError naming it."""
    if not isinstance(text, str) or not text.strip():
        raise UsageError("field path: empty (expected e.g. 'data', 'velocity[0]', 'twist.linear.x')")
    text = text.strip()
    steps = []
    for segment in text.split("."):
        match = _SEGMENT.match(segment)
        if not match:
            raise UsageError(
                f"field path {text!r}: bad segment {segment!r} (expected name, name[i] or name[:])"
            )
        indices = tuple(None if i == ":" else int(i) for i in _INDEX.findall(match.group(2)))
        if sum(i is None for i in indices) > 1:
            raise UsageError(f"field path {text!r}: at most one [:] per segment")
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


def extract_samples(msg: Any, path: FieldPath) -> np.ndarray:
    """The numbers at ``path`` in ``msg`` as a 1-D float array: one sample for a scalar field,
    every element for ``[:]`` or a numeric array field. Raises FieldError naming the field."""
    value = msg
    for step in path.steps:
        value = _attribute(value, step.name, path)
        for index in step.indices:
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
