"""One numeric field (and ``header.stamp``) read straight from a serialized ROS 2 message,
without building the Python message: the live node's fast path (rclpy ``raw=True``
subscriptions; rclpy's own deserialisation of a 100-double Float64MultiArray costs ~18 us, of
a JointState ~30 us, in the executor thread).

The layout is the message class's own introspection (``get_fields_and_field_types``), read
as OMG CDR (XCDR1), the encoding of rmw_fastrtps and of ROS 2 bags: a 4-byte encapsulation
header whose second byte gives the byte order, then the fields in order, each primitive
aligned to its size relative to the end of that header, strings and sequences as a uint32
count then their elements, nested messages inline, fixed arrays without a count.

The layout comes either from an installed message class's introspection
(``raw_extractor``, the node) or from the ``ros2msg`` schema text a bag stores beside its
messages (``schema_extractor``, replay: the bag's own definition, whatever is installed; parsed
by ``types.schema_fields``), as field name -> IDL type (``double``, ``sequence<double>``,
``std_msgs/Header``) in both cases. No message package is imported here: ``nested`` (type name
-> fields) is the caller's; ``hammer_ros.ros.message_types`` binds it to the installed packages.

``raw_extractor(cls, path, nested)`` returns ``extract(data) -> (values, stamp)`` with ``values`` the
samples of ``field_path.extract_samples`` (a float for one, else a float64 array) and ``stamp`` the
header stamp in seconds (0.0 for none), or None when the path cannot be read this way
(wide strings, a non-numeric target): the caller then subscribes to messages as usual.
``field[NAME]`` reads the ``name`` strings of the same message too and picks the element at
NAME's index (``field_path`` semantics: MissingName when a message lacks it). A
payload that is short or whose counts lie raises FieldError naming the field.
``extract_batch(extract, messages)`` reads the whole-array (or scalar) field of many messages
without a header at once, when they share one layout (the node's ingest of a flush).
``topic_decoder(cls, paths, nested)`` reads one number per path (``data[2]``, ``position[elbow]``) from
many messages at once, the layout walked once per distinct layout (a topic shared by channels).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .field_path import NAME_FIELD, FieldError, FieldPath, named_index
from .types import ARRAY_TYPE, SEQUENCE_TYPE, UnsupportedLayout, schema_fields

PRIMITIVES = {  # IDL type -> (struct code, size)
    "double": ("d", 8), "float": ("f", 4), "int64": ("q", 8), "uint64": ("Q", 8), "int32": ("i", 4),
    "uint32": ("I", 4), "int16": ("h", 2), "uint16": ("H", 2), "int8": ("b", 1), "uint8": ("B", 1),
    "char": ("B", 1), "octet": ("B", 1), "byte": ("B", 1), "boolean": ("?", 1),
}
HEADER = 4  # encapsulation header: 0x00, 0x01 (little endian) or 0x00 (big endian), options
_BOUNDED_STRING = re.compile(r"^string<\d+>$")

Skip = Callable[[bytes, int, str], int]  # (data, position after the header, byte order) -> position
Fields = Callable[[str], dict[str, str]]  # a nested type 'pkg/Name' -> its field names and IDL types
Extract = Callable[[bytes], tuple[float | np.ndarray, float]]  # serialized message -> (values, stamp)


def _align(pos: int, size: int, padding: list[tuple[int, int]] | None = None) -> int:
    """``pos`` rounded up to a multiple of ``size``; the alignment padding skipped appended to
    ``padding`` (as offsets into the serialized message) when given."""
    start = (pos + size - 1) & -size
    if padding is not None and start > pos:
        padding.append((HEADER + pos, HEADER + start))
    return start


def _u32(data: bytes, pos: int, order: str, padding: list[tuple[int, int]] | None = None) -> tuple[int, int]:
    """The uint32 at the next 4-aligned position and the position after it (``padding``: as ``_align``'s)."""
    start = _align(pos, 4, padding)
    return struct.unpack_from(order + "I", data, HEADER + start)[0], start + 4


def _kind(type_name: str, nested: Fields) -> tuple[str, Any, int | None]:
    """('primitive', code-size, count) / ('string', None, count) / ('message', fields, count);
    count None for one value, -1 for a sequence, k for a fixed array."""
    count: int | None = None
    match = SEQUENCE_TYPE.match(type_name)
    if match:
        type_name, count = match.group(1).strip(), -1
    else:
        match = ARRAY_TYPE.match(type_name)
        if match:
            type_name, count = match.group(1), int(match.group(2))
    if type_name in PRIMITIVES:
        return "primitive", PRIMITIVES[type_name], count
    if type_name == "string" or _BOUNDED_STRING.match(type_name):
        return "string", None, count
    if "/" in type_name:
        return "message", nested(type_name), count
    raise UnsupportedLayout(type_name)  # wstring and anything unknown


def _skipper(type_name: str, nested: Fields) -> Skip:
    """A function that moves past one field of ``type_name``."""
    kind, what, count = _kind(type_name, nested)
    if kind == "primitive":
        size = what[1]
        if count is None:
            return lambda data, pos, order: _align(pos, size) + size
        if count >= 0:
            return lambda data, pos, order: _align(pos, size) + count * size if count else pos

        def sequence(data: bytes, pos: int, order: str) -> int:
            n, pos = _u32(data, pos, order)
            return _align(pos, size) + n * size if n else pos
        return sequence
    one = _skip_string if kind == "string" else _message_skipper(what, nested)
    if count is None:
        return one

    def repeated(data: bytes, pos: int, order: str) -> int:
        n = count
        if n < 0:
            n, pos = _u32(data, pos, order)
            if n > len(data) - HEADER - pos:  # every element takes >= 1 byte: a count that lies
                raise struct.error("a sequence count beyond the end of the message")
        for _ in range(n):
            pos = one(data, pos, order)
        return pos
    return repeated


def _skip_string(data: bytes, pos: int, order: str) -> int:
    n, pos = _u32(data, pos, order)
    return pos + n


def _message_skipper(fields: dict[str, str], nested: Fields) -> Skip:
    skips = [_skipper(t, nested) for t in fields.values()]

    def skip(data: bytes, pos: int, order: str) -> int:
        for one in skips:
            pos = one(data, pos, order)
        return pos
    return skip


def _reader(type_name: str, indices: tuple[int | None, ...], path: FieldPath, nested: Fields) -> Callable:
    """Read the target field at a position: a float, a float64 array, or a Time in seconds."""
    kind, what, count = _kind(type_name, nested)
    if kind == "message" and count is None and not indices and \
            set(what) == {"sec", "nanosec"}:  # builtin_interfaces Time / Duration
        sec_code = PRIMITIVES[what["sec"]][0]

        def time(data: bytes, pos: int, order: str):
            pos = _align(pos, 4)
            sec, nanosec = struct.unpack_from(order + sec_code + "I", data, HEADER + pos)
            return float(sec + 1e-9 * nanosec)
        return time
    if kind != "primitive" or what[0] == "?" or len(indices) > (0 if count is None else 1):
        raise UnsupportedLayout(type_name)
    code, size = what
    dtype = np.dtype(code).newbyteorder("<")
    if count is None:
        def scalar(data: bytes, pos: int, order: str):
            return float(struct.unpack_from(order + code, data, HEADER + _align(pos, size))[0])
        scalar.located, scalar.dtype = (lambda data, pos, order: (HEADER + _align(pos, size), 1)), dtype
        scalar.single = True
        return scalar
    index = indices[0] if indices else None

    def located(data: bytes, pos: int, order: str) -> tuple[int, int]:
        """(byte offset in ``data``, element count) of the array at ``pos``."""
        n = count
        if n < 0:
            n, pos = _u32(data, pos, order)
        return HEADER + (_align(pos, size) if n else pos), n

    def elements(data: bytes, pos: int, order: str):
        start, n = located(data, pos, order)
        if start + n * size > len(data):
            raise FieldError(f"field {path.text!r}: the message ends inside it ({n} elements claimed)")
        values = np.frombuffer(data, dtype if order == "<" else dtype.newbyteorder(">"), n, start)
        if index is None:
            return values if values.dtype == np.float64 and order == "<" else values.astype(np.float64)
        if not -n <= index < n:
            raise FieldError(f"field {path.text!r}: index {index} out of range, {n} elements")
        return float(values[index])
    if index is None:  # the whole array: readable from many messages at once (``extract_batch``)
        elements.located, elements.dtype = located, dtype
    return elements


def raw_extractor(cls, path: FieldPath, nested: Fields) -> Extract | None:
    """``extract(data) -> (values, stamp)`` for serialized messages of ``cls`` (a message class
    with ``get_fields_and_field_types``; ``nested`` gives the fields of its nested types, see the
    module docstring), or None when ``path`` is not readable from raw CDR here."""
    try:
        return _extractor(cls.get_fields_and_field_types(), path, nested, whole=False)
    except (UnsupportedLayout, ImportError, AttributeError):
        return None


def schema_extractor(name: str, text: str, path: FieldPath) -> Extract | None:
    """``raw_extractor`` for messages of the ``ros2msg`` schema ``text`` of type ``name`` (a
    bag's own definition, ``schema_fields``), or None when the schema or the path cannot be read
    this way. ``extract`` also walks the rest of the message and raises FieldError when it ends
    early, so that a message it reads is one a full decoder reads too."""
    def nested(type_name: str) -> dict[str, str]:
        parts = type_name.split("/")
        try:
            return types[f"{parts[0]}/{parts[-1]}"]
        except KeyError:
            raise UnsupportedLayout(f"{type_name} is not in the schema") from None
    try:
        types = schema_fields(name, text)
        return _extractor(nested(name), path, nested, whole=True)
    except UnsupportedLayout:
        return None


def _strings(data: bytes, pos: int, order: str, count: int,
             padding: list[tuple[int, int]] | None = None) -> tuple[list[bytes], int]:
    """``count`` CDR strings at ``pos`` (-1: a sequence, its count first), without their NULs, and
    the position after them (``padding``: as ``_u32``'s)."""
    if count < 0:
        count, pos = _u32(data, pos, order, padding)
    out = []
    for _ in range(count):
        n, pos = _u32(data, pos, order, padding)
        out.append(bytes(data[HEADER + pos : HEADER + pos + max(n - 1, 0)]))
        pos += n
    return out, pos


def _named_reader(fields: dict[str, str], step, outer: list[Skip], path: FieldPath, nested: Fields) -> Callable:
    """The reader of ``field[NAME]``: the whole array, then its element at the index of NAME in
    the sibling ``name`` strings (``field_path.named_index``), both read from the message."""
    if NAME_FIELD not in fields or len(step.indices) != 1 or _kind(fields[step.name], nested)[2] is None:
        raise UnsupportedLayout(f"{step.name}[{step.element_name}]")
    kind, _, count = _kind(fields[NAME_FIELD], nested)
    if kind != "string" or count is None:
        raise UnsupportedLayout(fields[NAME_FIELD])
    names = list(fields)
    to_names = outer + [_skipper(fields[n], nested) for n in names[: names.index(NAME_FIELD)]]
    whole = _reader(fields[step.name], (), path, nested)
    element = step.element_name.encode()

    def named(data: bytes, pos: int, order: str) -> float:
        values = whole(data, pos, order)
        at = 0
        for skip in to_names:
            at = skip(data, at, order)
        found, _ = _strings(data, at, order, count)
        if element not in found:
            named_index([n.decode(errors="replace") for n in found], step.element_name, path)
        index = found.index(element)
        if not 0 <= index < np.size(values):
            raise FieldError(f"field {path.text!r}: {step.element_name!r} is name {index}, "
                             f"{step.name!r} has {np.size(values)} elements")
        return float(values[index])
    return named


def _extractor(fields: dict[str, str], path: FieldPath, nested: Fields, whole: bool) -> Extract | None:
    root = fields
    skips: list[Skip] = []  # the fields before the path's field, level by level
    for i, step in enumerate(path.steps):
        if step.name not in fields:
            return None
        outer = list(skips)
        names = list(fields)
        skips += [_skipper(fields[n], nested) for n in names[: names.index(step.name)]]
        if i < len(path.steps) - 1:
            kind, fields, count = _kind(fields[step.name], nested)
            if kind != "message" or count is not None or step.indices:
                return None
        elif step.element_name is not None:
            read = _named_reader(fields, step, outer, path, nested)
        else:
            read = _reader(fields[step.name], step.indices, path, nested)
    if "header" in root and (next(iter(root)) != "header" or root["header"] != "std_msgs/Header"):
        return None  # a header elsewhere: field_path.message_stamp's stamp is not read here
    stamp = _reader("builtin_interfaces/Time", (), path, nested) if "header" in root else None
    end = _message_skipper(root, nested) if whole else None

    def locate(data: bytes) -> tuple[int, int]:
        order = ">" if data[1] == 0 else "<"
        pos = 0
        for skip in skips:
            pos = skip(data, pos, order)
        return read.located(data, pos, order)

    # A message of the last one's length with the same bytes up to the field has the field at the
    # same place with the same count; when the field ends that message (nothing after it to walk),
    # it is read without walking: a bag's batch topic (Float64MultiArray, no header) costs one
    # comparison of its first bytes per message. (length, those bytes, offset, count, dtype).
    layout: list = []
    single = getattr(read, "single", False)
    memoised = stamp is None and end is not None and hasattr(read, "located")

    def remember(data: bytes, order: str) -> None:
        start, n = locate(data)
        if end(data, 0, order) + HEADER == start + n * read.dtype.itemsize:
            layout[:] = (len(data), bytes(data[:start]), start, n, read.dtype.newbyteorder(order))

    def extract(data: bytes) -> tuple[float | np.ndarray, float]:
        if layout and len(data) == layout[0] and data[: layout[2]] == layout[1]:
            values = np.frombuffer(data, layout[4], layout[3], layout[2])
            if single:
                return float(values[0]), 0.0
            return (values if values.dtype == np.float64 else values.astype(np.float64)), 0.0
        if len(data) < HEADER:
            raise FieldError(f"field {path.text!r}: a {len(data)}-byte message")
        order = ">" if data[1] == 0 else "<"
        try:
            pos = 0
            for skip in skips:
                pos = skip(data, pos, order)
            values = read(data, pos, order)
            if end is not None and end(data, 0, order) > len(data) - HEADER:
                raise struct.error("short")
            if memoised:
                remember(data, order)
            return values, (stamp(data, 0, order) if stamp is not None else 0.0)
        except struct.error:
            raise FieldError(f"field {path.text!r}: the message ends before it") from None
    if stamp is None and end is None and hasattr(read, "located"):
        extract.locate, extract.dtype = locate, read.dtype
    return extract


def extract_batch(extract: Extract, messages: list[bytes]) -> np.ndarray | None:
    """The samples of many serialized messages at once, as an (m, n) float64 array, for an
    ``extract`` of a whole array in messages without a header (``raw_extractor``): the array's
    place and length are found in the first message, and every other message must have the
    first one's length and the same bytes up to the array (so the same layout: its array is
    at the same place with the same count). None when ``extract`` cannot be batched or the
    messages differ: read them one by one (which also names what is wrong with a bad one)."""
    locate = getattr(extract, "locate", None)
    if locate is None or not messages:
        return None
    first = messages[0]
    if len(first) < HEADER or len(set(map(len, messages))) != 1:
        return None
    try:
        start, n = locate(first)
    except struct.error:
        return None
    width = n * extract.dtype.itemsize
    if start + width > len(first):
        return None
    block = np.frombuffer(b"".join(messages), np.uint8).reshape(len(messages), len(first))
    if start and not (block[:, :start] == block[0, :start]).all():
        return None
    order = ">" if first[1] == 0 else "<"
    values = block[:, start : start + width].copy().view(extract.dtype.newbyteorder(order))
    return values if values.dtype == np.float64 and order == "<" else values.astype(np.float64)


# ---------------------------------------------------------------- one pass for several fields
# A topic read by several channels (``channels.SharedTopic``) is decoded once per flush: the
# message's layout is walked once per distinct layout (``_walk``), and every field of a flush's
# messages is then read at its offset from one byte block with numpy.


@dataclass(frozen=True)
class Decoded:
    """The fields of m messages (``TopicDecoder.decode``): ``values[i, j]`` field j of message i
    (valid where ``bad[i, j]`` is False), ``stamps[i]`` its header stamp in seconds (0.0 for
    none), ``errors[j]`` why field j was bad in the last message where it was ('' if never)."""

    values: np.ndarray
    bad: np.ndarray
    stamps: np.ndarray
    errors: tuple[str, ...]


@dataclass(frozen=True)
class _Plan:
    """Where the fields are in messages of one layout: those of ``length`` bytes equal to
    ``reference`` at ``columns`` (every byte but the numbers', so the same counts, strings and
    padding: the walk of the layout goes the same way); ``offsets[j]`` the byte offset of field
    j (None: bad in this layout, ``errors[j]`` why)."""

    length: int
    columns: np.ndarray
    reference: np.ndarray
    offsets: tuple[int | None, ...]
    errors: tuple[str, ...]


def _walk(fields: dict[str, str], nested: Fields, data: bytes, order: str, pos: int, prefix: str,
          entries: dict[str, tuple], numbers: list[tuple[int, int]]) -> int:
    """Walk the fields at ``pos``: ``entries`` gets each number field ('scalar', offset, dtype),
    each number array ('array', offset, count, dtype) and each string array ('strings', the
    strings) by dotted name, outside sequences of messages; ``numbers`` the byte ranges of all
    numbers and of the alignment padding (the bytes that never change a layout: a serializer
    need not zero its padding). Returns the position after the fields."""
    for name, type_name in fields.items():
        kind, what, count = _kind(type_name, nested)
        key = prefix + name
        if kind == "primitive":
            code, size = what
            n = 1 if count is None else count
            if n < 0:
                n, pos = _u32(data, pos, order, numbers)
            start = _align(pos, size, numbers) if n else pos
            numbers.append((HEADER + start, HEADER + start + n * size))
            dtype = np.dtype(code).newbyteorder(order)
            entries[key] = ("scalar", HEADER + start, dtype) if count is None else ("array", HEADER + start, n, dtype)
            pos = start + n * size
        elif kind == "string":
            found, pos = _strings(data, pos, order, 1 if count is None else count, numbers)
            if count is not None:
                entries[key] = ("strings", found)
        elif count is None:
            pos = _walk(what, nested, data, order, pos, key + ".", entries, numbers)
        else:  # a sequence of messages: walked for its numbers, its fields not addressable
            n = count
            if n < 0:
                n, pos = _u32(data, pos, order, numbers)
                if n > len(data) - HEADER - pos:
                    raise struct.error("a sequence count beyond the end of the message")
            for _ in range(n):
                pos = _walk(what, nested, data, order, pos, key + "[].", {}, numbers)
    return pos


class TopicDecoder:
    """Fields ``paths`` (one number each: ``x``, ``data[3]``, ``position[elbow]``) of the
    serialized messages of one type, read in one pass (``decode``). A layout is walked once:
    its plan (the offsets, ``_Plan``) is kept for the messages that share it, the most recent
    first, at most MAX_PLANS (JointState's names rarely change: one plan)."""

    MAX_PLANS = 32

    def __init__(self, fields: dict[str, str], paths: list[FieldPath], nested: Fields) -> None:
        self.fields, self.paths, self.nested = fields, paths, nested
        self.stamped = "header" in fields
        if self.stamped and (next(iter(fields)) != "header" or fields["header"] != "std_msgs/Header"):
            raise UnsupportedLayout("a header elsewhere")
        for path in paths:
            self._target_kind(path)
        self._plans: list[_Plan] = []

    def _target_kind(self, path: FieldPath) -> str:
        """'scalar', 'index' or 'name' for a path to one number; UnsupportedLayout otherwise."""
        fields = self.fields
        for step in path.steps[:-1]:
            if step.name not in fields or step.indices:
                raise UnsupportedLayout(path.text)
            kind, fields, count = _kind(fields[step.name], self.nested)
            if kind != "message" or count is not None:
                raise UnsupportedLayout(path.text)
        last = path.steps[-1]
        if last.name not in fields:
            raise UnsupportedLayout(path.text)
        kind, what, count = _kind(fields[last.name], self.nested)
        if kind != "primitive" or what[0] == "?" or len(last.indices) != (0 if count is None else 1):
            raise UnsupportedLayout(path.text)
        if last.element_name is None:
            if last.indices and last.indices[0] is None:  # ``[:]``: every element, not one number
                raise UnsupportedLayout(path.text)
            return "index" if last.indices else "scalar"
        kind, _, count = _kind(fields.get(NAME_FIELD, "double"), self.nested)
        if kind != "string" or count is None:  # field[NAME] needs a sibling array of names
            raise UnsupportedLayout(path.text)
        return "name"

    def _plan(self, data: bytes) -> _Plan:
        """The plan of ``data``'s layout (FieldError when the message ends early)."""
        if len(data) < HEADER:
            raise FieldError(f"a {len(data)}-byte message")
        order = ">" if data[1] == 0 else "<"
        entries: dict[str, tuple] = {}
        numbers: list[tuple[int, int]] = []
        try:
            end = _walk(self.fields, self.nested, data, order, 0, "", entries, numbers)
        except struct.error:
            end = len(data)  # a count beyond the end
        if HEADER + end > len(data):
            raise FieldError("the message ends before its last field")
        offsets, errors = [], []
        for path in self.paths:
            try:
                offsets.append(self._offset(path, entries))
                errors.append("")
            except FieldError as exc:
                offsets.append(None)
                errors.append(str(exc))
        mask = np.ones(len(data), bool)
        for start, stop in numbers:
            mask[start:stop] = False
        columns = np.flatnonzero(mask)
        return _Plan(len(data), columns, np.frombuffer(data, np.uint8)[columns].copy(), tuple(offsets), tuple(errors))

    def _offset(self, path: FieldPath, entries: dict[str, tuple]) -> tuple[int, np.dtype]:
        """(byte offset, dtype) of ``path``'s number in a walked layout; FieldError as the
        one-message reader (``raw_extractor``) says it."""
        parents = [step.name for step in path.steps[:-1]]
        entry = entries[".".join([*parents, path.steps[-1].name])]
        if entry[0] == "scalar":
            return entry[1], entry[2]
        _, start, n, dtype = entry
        last = path.steps[-1]
        if last.element_name is None:
            index = last.indices[0]
            if not -n <= index < n:
                raise FieldError(f"field {path.text!r}: index {index} out of range, {n} elements")
            return start + (index % n) * dtype.itemsize, dtype
        names = entries[".".join([*parents, NAME_FIELD])][1]
        element = last.element_name.encode()
        if element not in names:
            named_index([s.decode(errors="replace") for s in names], last.element_name, path)
        index = names.index(element)
        if index >= n:
            raise FieldError(f"field {path.text!r}: {last.element_name!r} is name {index}, "
                             f"{last.name!r} has {n} elements")
        return start + index * dtype.itemsize, dtype

    def decode(self, messages: list[bytes]) -> Decoded:
        """Every field of ``messages`` (``Decoded``): the messages grouped by length into byte
        blocks, each block's rows matched to the kept plans at once, a new layout walked once."""
        m, k = len(messages), len(self.paths)
        values, bad, stamps = np.zeros((m, k)), np.zeros((m, k), bool), np.zeros(m)
        errors = [(-1, "")] * k  # (the last bad message, why) per field
        lengths = np.fromiter(map(len, messages), np.intp, m)
        for length in np.unique(lengths):
            rows = np.flatnonzero(lengths == length)
            block = np.frombuffer(b"".join([messages[i] for i in rows]), np.uint8).reshape(rows.size, length)
            left = np.arange(rows.size)
            while left.size:
                for plan in [p for p in self._plans if p.length == length]:
                    hit = (block[np.ix_(left, plan.columns)] == plan.reference).all(axis=1)
                    if hit.any():
                        self._apply(plan, block[left[hit]], rows[left[hit]], values, bad, stamps, errors)
                        left = left[~hit]
                        if not left.size:
                            break
                if not left.size:
                    break
                first = messages[rows[left[0]]]
                try:
                    self._plans.insert(0, self._plan(first))
                    del self._plans[self.MAX_PLANS:]
                except FieldError as exc:  # a message that cannot be walked: bad for every field
                    row = rows[left[0]]
                    bad[row] = True
                    errors[:] = [max(e, (row, f"field {p.text!r}: {exc}")) for e, p in zip(errors, self.paths)]
                    left = left[1:]
        return Decoded(values, bad, stamps, tuple(why for _, why in errors))

    def _apply(self, plan: _Plan, block: np.ndarray, rows: np.ndarray, values: np.ndarray, bad: np.ndarray,
               stamps: np.ndarray, errors: list[tuple[int, str]]) -> None:
        """Read ``plan``'s fields from ``block`` (a row per message, contiguous) into ``rows``."""
        def column(offset: int, dtype: np.dtype) -> np.ndarray:
            return np.ndarray(len(rows), dtype, block, offset, (plan.length,))
        for j, at in enumerate(plan.offsets):
            if at is None:
                bad[rows, j] = True
                errors[j] = max(errors[j], (rows[-1], plan.errors[j]))
            else:
                values[rows, j] = column(*at)
        if self.stamped:
            order = ">" if block[0, 1] == 0 else "<"
            stamps[rows] = column(HEADER, np.dtype(order + "i4")) + 1e-9 * column(HEADER + 4, np.dtype(order + "u4"))


def topic_decoder(cls, paths: list[FieldPath], nested: Fields) -> TopicDecoder | None:
    """A ``TopicDecoder`` of ``paths`` in serialized messages of ``cls`` (``nested``: as for
    ``raw_extractor``), or None when one of them is not one number readable this way (the caller
    reads each message as before)."""
    try:
        return TopicDecoder(cls.get_fields_and_field_types(), paths, nested)
    except (UnsupportedLayout, ImportError, AttributeError):
        return None
