"""Bags in, MCAP out: ``.mcap`` files and rosbag2 directories (``rosbag2``: metadata.yaml, MCAP or
SQLite files, split, zstd-compressed).

Reading uses ``mcap`` + ``mcap_ros2`` (CDR decoding from the ``ros2msg`` schemas stored in the
bag, so no ROS installation is needed; a ``.db3`` file is read as MCAP records by
``rosbag2_sqlite``). Only the topics asked for are decoded; other topics and unknown schemas
are skipped. Files are read sequentially and fault-tolerantly (``_RecordScan``):
a truncated or corrupt recording gives every valid message, with a warning saying where it
broke; oversized or undecodable messages are skipped and counted (``BagReadStats``).
A sample's stamp is the message's ``header.stamp`` when it has a header (an all-zero stamp is
no stamp: a warning names the topic once), else the bag's log time; a message with n samples
(``data[:]``, a numeric array field) follows the batch convention of ``field_path``.

Writing (``ResultWriter``) uses the ``mcap_ros2`` writer with the ``.msg`` definitions shipped in
``hammer_ros/data/ros2_msgs`` (Jazzy's, see the README there), so Foxglove Studio, rosbag2 and
``rosbags`` can open the file and deserialise every message; the JSON dashboard channels go into
a file of their own (``JsonWriter``, with their JSON schemas).
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import os
import re
import struct
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import UsageError
from ..identification.runs import Runs
from ..ros.field_path import FieldPath, extract_samples, message_stamp, message_stamp_ns, parse_field_path
from ..streaming.aligner import StreamAligner
from ..streaming.config import EngineConfig, EngineStats
from .records import Record
from .rosbag2 import BagLayout, decompress_message, read_layout, readable_file, storage_of
from .rosbag2_sqlite import SqliteScan, sqlite_index

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "data" / "ros2_msgs"
SCHEMA_SEPARATOR = "=" * 80
# msg_config keys that are not engine settings
TOPIC_KEYS = ("excitation_topic", "excitation_type", "excitation_field", "response_topic", "response_type",
              "response_field", "reference_topic", "reference_type", "reference_field")
OTHER_KEYS = ("solve_rate", "frame_id", "use_sim_time", "qos_depth", "max_pending", "output_mcap", "foxglove_port",
              "foxglove_host", "channels")
FLUSH_SAMPLES = 20_000  # buffered samples per vectorised engine update


# ------------------------------------------------------------------------------- specs and config
@dataclass(frozen=True)
class StreamSpec:
    """Where one signal is: a topic, the field path in its messages, optionally the type."""

    topic: str
    field: FieldPath
    type_name: str | None = None

    def __str__(self) -> str:
        return f"{self.topic}:{self.field}"


def parse_stream_spec(text: str, option: str) -> StreamSpec:
    """``/topic:field.path`` (e.g. ``/joint_states:velocity[0]``) -> StreamSpec."""
    topic, sep, path = (text or "").partition(":")
    if not sep or not topic.startswith("/") or not path:
        raise UsageError(f"{option}: expected /topic:field.path (e.g. /cmd:data), got {text!r}")
    try:
        return StreamSpec(topic, parse_field_path(path))
    except UsageError as exc:
        raise UsageError(f"{option}: {exc}") from None


def load_msg_config(path: str | Path) -> dict[str, Any]:
    """The parameters of a msg_config YAML in ROS 2 params-file form
    (``<node name>: {ros__parameters: {...}}``, e.g. ``hammer_ros`` or ``/**``)."""
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"{path}: no such config file")
    try:
        doc = yaml.safe_load(path.read_text())  # safe_load: plain data only, no Python objects
    except UnicodeDecodeError:
        raise UsageError(f"{path}: not a text (UTF-8) file") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise UsageError(f"{path}: not valid YAML{where} ({problem})") from None
    if isinstance(doc, dict):
        for section in doc.values():
            if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
                return dict(section["ros__parameters"])
    raise UsageError(f"{path}: expected a ROS 2 params file 'hammer_ros: {{ros__parameters: {{...}}}}'")


def engine_config_from_params(params: dict[str, Any], source: str = "config",
                              base: EngineConfig | None = None) -> EngineConfig:
    """An EngineConfig from node-style parameters (unknown keys are an error naming them; ROS
    parameters cannot be null, so ``mu: 0`` and ``partition: []`` mean the method's default)."""
    fields = set(EngineConfig.__dataclass_fields__)
    changes = {}
    for key, value in params.items():
        if key in TOPIC_KEYS or key in OTHER_KEYS:
            continue
        if key not in fields:
            known = ", ".join(sorted(fields | set(TOPIC_KEYS) | set(OTHER_KEYS)))
            raise UsageError(f"{source}: unknown parameter {key!r} (known: {known})")
        if key == "mu" and value in (0, None):
            value = None
        elif key == "partition":
            if value is not None and not isinstance(value, (list, tuple)):
                raise UsageError(f"{source}: partition: must be a list of breakpoints, e.g. [-0.5, 0.5] "
                                 f"(got {value!r})")
            value = tuple(value) if value else None
        changes[key] = value
    try:
        config = EngineConfig(**{**(base or EngineConfig()).__dict__, **changes})
        return config.validated()
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{source}: {exc}") from None


def stream_specs(input_spec: str | None, output_spec: str | None, params: dict[str, Any] | None,
                 source: str = "config") -> tuple[StreamSpec, StreamSpec]:
    """(excitation, response) from --input/--output, falling back to the config's topics/fields."""
    return (stream_spec("--input", "excitation", input_spec, params, source),
            stream_spec("--output", "response", output_spec, params, source))


def stream_spec(option: str, role: str, text: str | None, params: dict[str, Any] | None, source: str = "config",
                required: bool = True) -> StreamSpec | None:
    """One stream from its option (``/topic:field``), else the config's ``<role>_topic`` and
    ``<role>_field`` (``_type`` optional); without either: a UsageError, or None when not ``required``."""
    if text:
        return parse_stream_spec(text, option)
    params = params or {}
    topic, field = params.get(f"{role}_topic"), params.get(f"{role}_field")
    if not topic or not field:
        if required or topic or field:
            raise UsageError(f"{option}: give /topic:field or a --config with {role}_topic and {role}_field")
        return None
    try:
        return StreamSpec(str(topic), parse_field_path(str(field)), params.get(f"{role}_type"))
    except UsageError as exc:
        raise UsageError(f"{source}: {role}_field: {exc}") from None


@dataclass(frozen=True)
class Channel:
    """One (excitation, response) pair of a ``channels`` list: its name, streams and parameters
    (the file's top-level parameters with the channel's own overrides)."""

    name: str
    excitation: StreamSpec
    response: StreamSpec
    params: dict


_CHANNEL_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def config_channels(params: dict[str, Any], source: str = "config") -> list[Channel]:
    """The channels of a msg_config / params file, [] without a ``channels`` list. Two forms:
    ``channels: [shoulder, elbow]`` with each channel's parameters under its name
    (``shoulder: {response_field: "velocity[shoulder_joint]", order: 2}``: the form a ROS 2
    params file can hold, nested names becoming ``shoulder.response_field``), or a list of
    mappings each with a ``name``. The top-level parameters are every channel's defaults. A
    name that is not a ROS name token, a duplicate, or a bad parameter is a UsageError naming
    the file and the channel."""
    listed = params.get("channels")
    if listed is None or listed == []:
        return []
    if not isinstance(listed, list) or not (all(isinstance(c, str) for c in listed)
                                            or all(isinstance(c, dict) for c in listed)):
        raise UsageError(f"{source}: channels: expected a list of channel names (each with its parameters under "
                         "its name) or a list of mappings with a name")
    names = [c if isinstance(c, str) else c.get("name") for c in listed]
    for index, name in enumerate(names):
        if not isinstance(name, str) or not _CHANNEL_NAME.match(name):
            raise UsageError(f"{source}: channels[{index}]: name {name!r} must be a name like shoulder_pan "
                             "(letters, digits, _; a letter first)")
        if name in names[:index]:
            raise UsageError(f"{source}: channels: duplicate channel {name!r}")
    stray = next((k for k, v in params.items() if isinstance(v, dict) and k not in names), None)
    if stray is not None:
        raise UsageError(f"{source}: {stray}: parameters of a channel {stray!r} that is not in channels "
                         f"({', '.join(names)})")
    entries = [{"name": c, **_channel_section(params, c, source)} if isinstance(c, str) else c for c in listed]
    named = {c for c in listed if isinstance(c, str)}
    base = {k: v for k, v in params.items() if k != "channels" and str(k).split(".", 1)[0] not in named}
    channels: list[Channel] = []
    for entry in entries:
        name = entry["name"]
        merged = {**base, **{k: v for k, v in entry.items() if k != "name"}}
        where = f"{source}: channel {name!r}"
        engine_config_from_params(merged, where)  # unknown or bad parameters, named
        excitation, response = stream_specs(None, None, merged, where)
        channels.append(Channel(name, excitation, response, merged))
    return channels


def single_channel_params(params: dict[str, Any], source: str, why: str) -> dict[str, Any]:
    """``params`` of a file without channels, the parameters of its only channel, or a UsageError
    (naming the file, its channels and ``why``) for several."""
    channels = config_channels(params, source)
    if len(channels) > 1:
        raise UsageError(f"--config: {source} has {len(channels)} channels ({', '.join(c.name for c in channels)}); "
                         f"{why}")
    return channels[0].params if channels else params


def _channel_section(params: dict[str, Any], name: str, source: str) -> dict[str, Any]:
    """The parameters under a channel's name (nested, or ``name.key`` flattened); {} for none."""
    section = params.get(name, {})
    if not isinstance(section, dict):
        raise UsageError(f"{source}: {name}: the parameters of channel {name!r} must be a mapping")
    dotted = {k.split(".", 1)[1]: v for k, v in params.items() if isinstance(k, str) and k.startswith(f"{name}.")}
    return {**section, **dotted}


# ------------------------------------------------------------------------------- reading
MAX_RECORD_BYTES = 256 * 2**20  # an MCAP record (chunk) claiming more is treated as damage, never allocated
MAX_MESSAGE_BYTES = 16 * 2**20  # a message larger than this (2 M float64 samples) is skipped and counted
MAX_RECORD_SAMPLES = 10_000_000  # identify/diagnose hold the aligned record in memory: at most this many samples
FIELD_CHECK_MESSAGES = 100  # a field path must work in one of the first messages of its topic
_warned: set[str] = set()


def warn(text: str) -> None:
    """One ``hammer-ros: warning:`` line on stderr (each distinct text once per command:
    ``forget_warnings`` starts a command)."""
    if text not in _warned:
        _warned.add(text)
        print(f"hammer-ros: warning: {text}", file=sys.stderr)


def forget_warnings() -> None:
    _warned.clear()


@dataclass
class BagReadStats:
    """What reading a bag skipped; nothing is dropped silently (``warnings`` says what and why)."""

    damage: list[str] = field(default_factory=list)  # where a file is truncated or corrupt
    oversized: int = 0  # messages larger than MAX_MESSAGE_BYTES
    undecodable: int = 0  # messages whose CDR bytes do not decode with their schema
    field_errors: dict[str, int] = field(default_factory=dict)  # topic -> messages without the field
    first_error: dict[str, str] = field(default_factory=dict)  # kind or topic -> the first reason
    zero_stamps: dict[str, int] = field(default_factory=dict)  # topic -> messages whose header stamp is zero

    def note(self, key: str, reason: str) -> None:
        self.first_error.setdefault(key, reason)

    def warnings(self, path: str | Path) -> list[str]:
        lines = list(self.damage)
        if self.oversized:
            lines.append(f"{path}: {self.oversized} message(s) over {MAX_MESSAGE_BYTES // 2**20} MiB skipped "
                         f"({self.first_error['oversized']})")
        if self.undecodable:
            lines.append(f"{path}: {self.undecodable} message(s) that do not decode skipped "
                         f"({self.first_error['undecodable']})")
        lines.extend(f"{path}: {n} message(s) on {topic} skipped ({self.first_error[topic]})"
                     for topic, n in self.field_errors.items())
        lines.extend(f"{path}: {topic}: header.stamp is zero (no stamp) in {n} message(s): placed at their log time"
                     for topic, n in self.zero_stamps.items())
        return lines

    def report(self, path: str | Path) -> None:
        for line in self.warnings(path):
            warn(line)


def bag_layout(path: str | Path) -> BagLayout:
    """The files of a bag and their compression (``rosbag2.read_layout``), its note warned."""
    layout = read_layout(path)
    if layout.note:
        warn(layout.note)
    return layout


def bag_files(path: str | Path) -> list[Path]:
    """The files of a bag in reading order: a .mcap/.db3 file, or a rosbag2 directory's."""
    return list(bag_layout(path).files)


class _RecordScan:
    """A sequential, fault-tolerant read of one MCAP file (no summary needed, so an unfinished
    recording is read too). ``groups()`` yields the records of each chunk as one list (a record
    outside chunks as a list of one). A chunk that fails its CRC, decompression or parsing is
    skipped; a record that cannot be read ends the file (its length is unknown, nothing after it
    can be found). ``damage`` says where, in bytes from the start of the file."""

    def __init__(self, file: Path) -> None:
        self.file = file
        self.damage: list[str] = []
        self.header_seen = False
        self.messages = 0  # message records read (chunks included)

    def groups(self) -> Iterator[list[Any]]:
        from mcap.exceptions import McapError
        from mcap.records import Chunk, Header
        from mcap.stream_reader import StreamReader

        source = readable_file(self.file)
        size = source.stat().st_size
        with open(source, "rb") as fh:
            records = StreamReader(fh, emit_chunks=True, record_size_limit=MAX_RECORD_BYTES).records
            offset = 0
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except (McapError, ValueError, EOFError, OSError, struct.error) as exc:
                    truncated = isinstance(exc, (EOFError, struct.error)) or type(exc).__name__ == "EndOfFile"
                    what = "truncated: the file ends inside the record" if truncated else f"unreadable ({_reason(exc)})"
                    self.damage.append(f"{what} at byte {offset:,} of {size:,}; "
                                       f"read the {self.messages} messages before it")
                    return
                if isinstance(record, Header):
                    self.header_seen = True
                group = self._chunk(record, offset) if isinstance(record, Chunk) else [record]
                self.messages += sum(type(r).__name__ == "Message" for r in group)
                if group:
                    yield group
                offset = fh.tell()

    def _chunk(self, chunk, offset: int) -> list[Any]:
        if chunk.uncompressed_size > MAX_RECORD_BYTES:
            self.damage.append(f"chunk at byte {offset:,} claims {chunk.uncompressed_size:,} bytes; skipped")
            return []
        try:
            return chunk_records(chunk)
        except Exception as exc:  # damaged data fails in many ways inside zstd/lz4/the parser
            self.damage.append(f"chunk at byte {offset:,} is corrupt ({_reason(exc)}); skipped")
            return []


_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
MESSAGE_OPCODE, CHANNEL_OPCODE, SCHEMA_OPCODE = 0x05, 0x04, 0x03


def chunk_records(chunk) -> list[Any]:
    """The Schema, Channel and Message records of an MCAP chunk (what ``mcap``'s
    ``breakup_chunk`` with CRC validation gives), its message records parsed with one
    ``struct`` call each instead of mcap's stream reader (about 3x less time per message).
    Raises on a CRC mismatch or a record that overruns the chunk."""
    from io import BytesIO

    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Message, Schema

    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"unknown chunk compression {chunk.compression!r}")
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError(f"chunk CRC mismatch ({zlib.crc32(data)} vs {chunk.uncompressed_crc})")
    records: list[Any] = []
    pos, end = 0, len(data)
    while pos < end:
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        body, pos = pos + _RECORD_HEAD.size, pos + _RECORD_HEAD.size + length
        if pos > end:
            raise ValueError(f"a record of {length:,} bytes overruns the chunk")
        if opcode == MESSAGE_OPCODE:
            channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, body)
            records.append(Message(channel_id=channel_id, log_time=log_time, publish_time=publish_time,
                                   sequence=sequence, data=data[body + _MESSAGE_HEAD.size : pos]))
        elif opcode in (CHANNEL_OPCODE, SCHEMA_OPCODE):
            stream = ReadDataStream(BytesIO(data[body:pos]))
            records.append(Channel.read(stream) if opcode == CHANNEL_OPCODE else Schema.read(stream))
    return records


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@dataclass(frozen=True, eq=False)
class FileIndex:
    """The schemas, channels and message counts of one MCAP file (from its summary, else from a
    scan of its records); ``damage`` says where the scan found it broken."""

    file: Path
    schemas: dict[int, Any]
    channels: dict[int, Any]
    counts: dict[int, int]
    damage: tuple[str, ...]
    span: tuple[int, int] | None = None  # log times (ns) of the first and the last message


def file_index(file: Path) -> FileIndex:
    stat = file.stat()
    return _file_index(str(file), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=32)
def _file_index(file: str, mtime_ns: int, size: int) -> FileIndex:
    from mcap.exceptions import InvalidMagic, McapError
    from mcap.reader import SeekingReader
    from mcap.records import Channel, Message, Schema

    path = Path(file)
    if storage_of(path) == "sqlite3":
        schemas, channels, counts, span, damage = sqlite_index(path, readable_file(path), message_definition)
        return FileIndex(path, schemas, channels, counts, damage, span)
    summary = None
    try:
        with open(readable_file(path), "rb") as fh:
            summary = SeekingReader(fh, record_size_limit=MAX_RECORD_BYTES).get_summary()
    except InvalidMagic:
        raise UsageError(f"{path}: not an MCAP file (wrong magic bytes)") from None
    except (McapError, ValueError, EOFError, OSError, struct.error):
        summary = None  # no footer or summary: an unfinished or damaged recording, scanned below
    if summary is not None and summary.statistics is not None:
        stats = summary.statistics
        span = (stats.message_start_time, stats.message_end_time) if stats.message_count else None
        return FileIndex(path, dict(summary.schemas), dict(summary.channels), dict(stats.channel_message_counts),
                         (), span)
    scan = _RecordScan(path)
    schemas, channels, counts = {}, {}, {}
    first = last = None
    for group in scan.groups():
        for record in group:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                first = record.log_time if first is None else min(first, record.log_time)
                last = record.log_time if last is None else max(last, record.log_time)
    if not scan.header_seen:
        reason = scan.damage[0] if scan.damage else "no MCAP header record"
        raise UsageError(f"{path}: not a readable MCAP file ({'empty file' if size == 0 else reason})")
    return FileIndex(path, schemas, channels, counts, tuple(scan.damage), None if first is None else (first, last))


def bag_topics(path: str | Path) -> dict[str, str]:
    """topic -> ROS type name of every channel in the bag."""
    topics = {}
    for file in bag_files(path):
        index = file_index(file)
        for channel in index.channels.values():
            schema = index.schemas.get(channel.schema_id)
            topics[channel.topic] = schema.name if schema else ""
    return topics


def bag_message_counts(path: str | Path) -> dict[str, int]:
    """topic -> number of messages (from the MCAP summaries, else counted by a scan)."""
    counts: dict[str, int] = {}
    for file in bag_files(path):
        index = file_index(file)
        for channel_id, count in index.counts.items():
            channel = index.channels.get(channel_id)
            if channel is not None:
                counts[channel.topic] = counts.get(channel.topic, 0) + count
    return counts


def bag_duration(path: str | Path) -> float:
    """Seconds from the first to the last message of the bag (log times; 0 when it has none)."""
    spans = [s for s in (file_index(f).span for f in bag_files(path)) if s is not None]
    return 1e-9 * (max(s[1] for s in spans) - min(s[0] for s in spans)) if spans else 0.0


def check_topics(path: str | Path, specs: tuple[StreamSpec, ...]) -> dict[str, str]:
    """The bag's topic types; a UsageError when a spec's topic is absent, of another type, or
    not decodable (not ROS 2 CDR with a ros2msg schema). Other topics are never decoded, so
    unknown schemas there do not matter."""
    topics = bag_topics(path)
    for spec in specs:
        if spec.topic not in topics:
            damage = [d for f in bag_files(path) for d in file_index(f).damage]
            note = f"; damaged file: {damage[0]}" if damage else ""
            raise UsageError(f"{path}: no topic {spec.topic!r} (topics: {', '.join(sorted(topics)) or 'none'}){note}")
        wanted, found = _normal_type(spec.type_name), _normal_type(topics[spec.topic])
        if wanted and found and wanted != found:
            raise UsageError(f"{path}: topic {spec.topic} has type {topics[spec.topic]}, config says {spec.type_name}")
    wanted_topics = {spec.topic for spec in specs}
    for file in bag_files(path):
        decoders = _Decoders(file_index(file))
        for channel in decoders.index.channels.values():
            if channel.topic in wanted_topics:
                decoders.get(channel)
    return topics


def _normal_type(name: str | None) -> str:
    """'pkg/msg/Name' and 'pkg/Name' compare equal."""
    if not name:
        return ""
    parts = name.split("/")
    return f"{parts[0]}/{parts[-1]}"


class _Decoders:
    """CDR decoders of one file's channels, built from the ros2msg schemas stored in the bag."""

    def __init__(self, index: FileIndex) -> None:
        from mcap_ros2.decoder import DecoderFactory

        self.index = index
        self.schemas = dict(index.schemas)
        self.channels = dict(index.channels)
        self._factory = DecoderFactory()
        self._decoders: dict[int, Any] = {}

    def get(self, channel) -> Any:
        decoder = self._decoders.get(channel.id)
        if decoder is not None:
            return decoder
        schema = self.schemas.get(channel.schema_id)
        where = f"{self.index.file}: topic {channel.topic}"
        if schema is None:
            raise UsageError(f"{where}: no schema stored for it, cannot decode")
        if not schema.data:  # a .db3 without message definitions (Humble's) of a type hammer_ros does not ship
            raise UsageError(f"{where}: no definition of {schema.name} in the bag nor installed, cannot decode")
        try:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                decoder = self._factory.decoder_for(channel.message_encoding, schema)  # (the parser prints)
        except Exception as exc:  # the schema text comes from the file: any parse failure
            raise UsageError(f"{where}: cannot parse its schema {schema.name!r} ({_reason(exc)})") from None
        if decoder is None:
            raise UsageError(f"{where}: {channel.message_encoding!r} messages with a {schema.encoding!r} schema "
                             "are not ROS 2 CDR/ros2msg, cannot decode")
        self._decoders[channel.id] = decoder
        return decoder


RECENT_BYTES = 1 << 20  # messages this big are kept decoded (at most RECENT_COUNT): check_fields, then the read
RECENT_COUNT = 2
_recently_decoded: dict[tuple, Any] = {}


_SKIPPED = object()  # what a decode function returns for a message it skipped (and counted)


def _decode_message(file: Path, decoders: _Decoders, channel, record, stats: BagReadStats) -> Any:
    """The message decoded with its schema (mcap_ros2), or _SKIPPED (counted) when it does not decode."""
    key = (str(file), channel.id, record.sequence, record.log_time)
    decoded = _recently_decoded.get(key)
    try:
        decoded = decoders.get(channel)(record.data) if decoded is None else decoded
    except Exception as exc:  # corrupt CDR bytes fail in many ways
        stats.undecodable += 1
        stats.note("undecodable", f"{channel.topic}: {_reason(exc)}")
        return _SKIPPED
    if len(record.data) > RECENT_BYTES and key not in _recently_decoded:
        while len(_recently_decoded) >= RECENT_COUNT:
            _recently_decoded.pop(next(iter(_recently_decoded)))
        _recently_decoded[key] = decoded
    return decoded


def _bag_records(path: str | Path, topics: list[str], stats: BagReadStats, decode) -> Iterator[tuple[int, str, Any]]:
    """(log time in ns, topic, ``decode(file, decoders, channel, record, stats)``) of ``topics``
    in log-time order (per chunk; files merged by log time). Damaged chunks and messages over
    MAX_MESSAGE_BYTES are skipped and counted in ``stats``, and so are the messages ``decode``
    returns _SKIPPED for."""
    import heapq

    from mcap.records import Channel, Message, Schema

    wanted = set(topics)
    layout = bag_layout(path)

    def one_file(file: Path):
        decoders = _Decoders(file_index(file))
        scan = _RecordScan(file) if storage_of(file) == "mcap" else SqliteScan(
            file, readable_file(file), [c.id for c in decoders.channels.values() if c.topic in wanted])
        for group in scan.groups():
            messages = []
            for record in group:
                if isinstance(record, Message):
                    channel = decoders.channels.get(record.channel_id)
                    if channel is not None and channel.topic in wanted:
                        messages.append((record.log_time, channel, record))
                elif isinstance(record, Channel):
                    decoders.channels.setdefault(record.id, record)
                elif isinstance(record, Schema):
                    decoders.schemas.setdefault(record.id, record)
            messages.sort(key=lambda m: m[0])
            for log_time, channel, record in messages:
                if layout.message_compressed:
                    try:
                        record = replace(record, data=decompress_message(record.data, MAX_MESSAGE_BYTES + 1))
                    except ValueError as exc:
                        stats.undecodable += 1
                        stats.note("undecodable", f"{channel.topic}: {exc}")
                        continue
                if len(record.data) > MAX_MESSAGE_BYTES:
                    stats.oversized += 1
                    stats.note("oversized", f"{channel.topic}: {len(record.data):,} bytes")
                    continue
                decoded = decode(file, decoders, channel, record, stats)
                if decoded is not _SKIPPED:
                    yield log_time, channel.topic, decoded
        stats.damage.extend(f"{file}: {d}" for d in scan.damage if f"{file}: {d}" not in stats.damage)

    yield from heapq.merge(*(one_file(f) for f in layout.files), key=lambda m: m[0])


def iter_bag_messages(path: str | Path, topics: list[str],
                      stats: BagReadStats | None = None) -> Iterator[tuple[str, int, Any]]:
    """(topic, log time in ns, decoded message) of ``topics`` in log-time order (per chunk;
    files merged by log time). Damaged chunks, messages over MAX_MESSAGE_BYTES and messages that
    do not decode are skipped and counted in ``stats``; only ``topics`` are decoded."""
    stats = stats if stats is not None else BagReadStats()
    for log_time, topic, decoded in _bag_records(path, topics, stats, _decode_message):
        yield topic, log_time, decoded


def check_fields(path: str | Path, specs: tuple[StreamSpec, ...]) -> None:
    """A UsageError when a spec's topic has no messages or its field is in none of the first
    FIELD_CHECK_MESSAGES messages of the topic (later messages without it are skipped and counted)."""
    counts = bag_message_counts(path)
    for spec in specs:
        if not counts.get(spec.topic):
            raise UsageError(f"{path}: topic {spec.topic} has no messages")
    pending = {spec.topic: [s for s in specs if s.topic == spec.topic] for spec in specs}
    first_error: dict[str, str] = {}
    tried: dict[str, int] = {}
    read = BagReadStats()
    for topic, _, msg in iter_bag_messages(path, list(pending), read):
        for spec in list(pending.get(topic, ())):
            try:
                extract_samples(msg, spec.field)
                pending[topic].remove(spec)
            except UsageError as exc:
                first_error.setdefault(topic, str(exc))
        tried[topic] = tried.get(topic, 0) + 1
        pending = {t: s for t, s in pending.items() if s}
        if not pending or any(tried.get(t, 0) >= FIELD_CHECK_MESSAGES for t in pending):
            break
    for topic in pending:
        problems = read.warnings(path)
        reason = first_error.get(topic) or "no message could be read" + (f" ({problems[0]})" if problems else "")
        raise UsageError(f"{path}: topic {topic}: {reason}")


@dataclass(frozen=True, eq=False)
class BagSample:
    """The samples one message contributes to a stream."""

    stream: Any  # "excitation" or "response" (or the role given to ``iter_role_samples``)
    stamp: float  # header stamp or log time (s): the time of the LAST sample
    values: np.ndarray | float  # a float: one sample
    log_time: int  # ns
    stamp_ns: int  # ``stamp`` exactly, in integer ns (float seconds of an epoch time are 238 ns apart)


def iter_bag_samples(path: str | Path, excitation: StreamSpec, response: StreamSpec,
                     stats: BagReadStats | None = None) -> Iterator[BagSample]:
    """The excitation and response samples of the bag, message by message in log-time order.
    When both specs name the same topic, each message feeds both streams. A message without the
    field is skipped and counted in ``stats.field_errors`` (``check_fields`` first rejects a field
    that no message has).

    Each field is read straight from the serialized message with the layout of the bag's own
    ``ros2msg`` schema (``cdr.schema_extractor``: no message is built, ~10x less time per
    100-double message than decoding it); a message it cannot read (or a schema it cannot parse)
    is decoded in full, which names what is wrong exactly as before."""
    check_topics(path, (excitation, response))
    return iter_role_samples(path, [("excitation", excitation), ("response", response)], stats)


def iter_role_samples(path: str | Path, specs: list[tuple[Any, StreamSpec]],
                      stats: BagReadStats | None = None) -> Iterator[BagSample]:
    """``iter_bag_samples`` for any number of (role, spec) pairs (the roles of several channels:
    ``BagSample.stream`` is the role): each topic is read once per message, and every spec on
    it is read from that one message."""
    stats = stats if stats is not None else BagReadStats()
    roles: dict[str, list[tuple[Any, StreamSpec]]] = {}
    for role, spec in specs:
        roles.setdefault(spec.topic, []).append((role, spec))
    readers: dict[tuple[str, int], list | None] = {}
    headed: dict[str, bool] = {}  # topic -> its messages start with a std_msgs/Header (a zero stamp: none)

    def decode(file: Path, decoders: _Decoders, channel, record, stats: BagReadStats) -> Any:
        key = (str(file), channel.id)
        if key not in readers:
            readers[key] = _field_readers(decoders, channel, roles[channel.topic])
            headed[channel.topic] = _starts_with_header(decoders, channel)
        extractors = readers[key]
        if extractors is not None:
            try:
                return _Read([extract(record.data) for extract in extractors], header_stamp_ns(record.data))
            except (UsageError, ValueError, IndexError):
                pass  # the full decode says what is wrong
        return _decode_message(file, decoders, channel, record, stats)

    for log_time, topic, msg in _bag_records(path, list(roles), stats, decode):
        if isinstance(msg, _Read):
            stamp, stamp_ns = (msg.fields[0][1], msg.stamp_ns) if msg.fields[0][1] else (log_time * 1e-9, log_time)
            if not msg.fields[0][1] and headed.get(topic):
                stats.zero_stamps[topic] = stats.zero_stamps.get(topic, 0) + 1
            for (role, _), (values, _) in zip(roles[topic], msg.fields, strict=True):
                yield BagSample(role, stamp, values, log_time, stamp_ns)
            continue
        stamp = message_stamp(msg)
        if stamp == 0.0:  # a header without a stamp (None: no header)
            stats.zero_stamps[topic] = stats.zero_stamps.get(topic, 0) + 1
        stamp, stamp_ns = (log_time * 1e-9, log_time) if not stamp else (stamp, message_stamp_ns(msg))
        for role, spec in roles[topic]:
            try:
                values = extract_samples(msg, spec.field)
            except UsageError as exc:
                stats.field_errors[topic] = stats.field_errors.get(topic, 0) + 1
                stats.note(topic, str(exc))
                continue
            yield BagSample(role, stamp, values, log_time, stamp_ns)


def header_stamp_ns(data: bytes) -> int:
    """The header stamp (integer ns) of a serialized message whose first field is a
    std_msgs/Header (what ``cdr`` reads a stamp from: sec, nanosec right after the 4-byte
    encapsulation); meaningless for other messages, whose stamp ``cdr`` reports as 0."""
    if len(data) < 12:
        return 0
    sec, nanosec = struct.unpack_from(">iI" if data[1] == 0 else "<iI", data, 4)
    return sec * 1_000_000_000 + nanosec


@dataclass(frozen=True, eq=False)
class _Read:
    """(values, stamp) of each role's field, read from the serialized message, and its header
    stamp in integer ns."""

    fields: list
    stamp_ns: int


def _starts_with_header(decoders: _Decoders, channel) -> bool:
    """Whether the channel's ros2msg schema starts with a std_msgs/Header (``header_stamp_ns``)."""
    schema = decoders.schemas.get(channel.schema_id)
    if schema is None or schema.encoding != "ros2msg":
        return False
    lines = (line.split("#")[0].split() for line in schema.data.decode(errors="replace").splitlines())
    first = next((words for words in lines if words), [])
    return first[:1] in (["std_msgs/Header"], ["Header"], ["std_msgs/msg/Header"])


def _field_readers(decoders: _Decoders, channel, specs: list[tuple[str, StreamSpec]]) -> list | None:
    """``cdr.schema_extractor`` of each spec's field on this channel, or None (decode in full)
    when the channel is not CDR with a ros2msg schema or one field cannot be read that way."""
    from ..ros.cdr import schema_extractor

    schema = decoders.schemas.get(channel.schema_id)
    if schema is None or channel.message_encoding != "cdr" or schema.encoding != "ros2msg":
        return None
    try:
        text = schema.data.decode()
    except UnicodeDecodeError:
        return None
    extractors = [schema_extractor(schema.name, text, spec.field) for _, spec in specs]
    return None if any(e is None for e in extractors) else extractors


def load_bag_record(path: str | Path, input_spec: str | None = None, output_spec: str | None = None,
                    config: str | Path | None = None, reference_spec: str | None = None) -> Record:
    """All aligned samples of a bag as a Record (the streaming engine's alignment, without the
    window): used by ``identify``/``diagnose`` on bags. The gap-free segments (a gap: the
    aligner's, a silence longer than ``max_gap``) are the record's runs, separate experiments
    (``Record.runs``; None for one segment; a note on stderr says how many). At most MAX_RECORD_SAMPLES samples
    (a longer bag is a UsageError pointing to ``replay``, which keeps only a window).

    ``reference_spec`` (``--reference /topic:field``, else the config's ``reference_topic`` and
    ``reference_field``; a closed loop's reference): aligned with
    the excitation the same way, then read at the record's sample times (linear interpolation;
    on the common grid these are its own samples)."""
    forget_warnings()
    params = load_msg_config(config) if config else {}
    params = single_channel_params(params, str(config), "identify and diagnose read one pair (--input/--output, "
                                   "or replay for every channel)")
    engine_config = engine_config_from_params(params, str(config or "config"))
    excitation, response = stream_specs(input_spec, output_spec, params, str(config or "config"))
    reference = stream_spec("--reference", "reference", reference_spec, params, str(config or "config"),
                            required=False)
    t, v, y, runs = _aligned_samples(path, excitation, response, engine_config)
    if reference is None:
        return Record(v, y, t, str(path), runs=runs)
    try:
        t_r, _, r, _ = _aligned_samples(path, excitation, reference, engine_config)
    except UsageError as exc:
        raise UsageError(f"--reference: {exc}") from None
    return Record(v, y, t, str(path), np.interp(t, t_r, r), runs)


def _aligned_samples(path: str | Path, excitation: StreamSpec, response: StreamSpec,
                     engine_config: EngineConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, Runs | None]:
    """(t, v, y, runs): every aligned sample of the two streams and its gap-free segments as
    runs (None: one segment) (``load_bag_record``)."""
    check_topics(path, (excitation, response))
    check_fields(path, (excitation, response))
    chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    segments: list[int] = [0]  # the first chunk of each segment
    stats = EngineStats(sample_rate=engine_config.sample_rate)
    aligner = StreamAligner(engine_config, stats, lambda t, v, y: chunks.append((t, v, y)),
                            lambda: segments.append(len(chunks)))
    read = BagReadStats()
    for sample in iter_bag_samples(path, excitation, response, read):
        aligner.add_message(sample.stream, sample.stamp, sample.values, flush=False)
        if aligner.buffered >= FLUSH_SAMPLES:
            aligner.flush()
            if stats.aligned > MAX_RECORD_SAMPLES:
                raise UsageError(f"{path}: more than {MAX_RECORD_SAMPLES:,} aligned samples, too many to identify "
                                 "in one batch; use `hammer-ros replay` (a sliding window) or cut the bag")
    aligner.flush()
    read.report(path)
    if not chunks:
        raise UsageError(f"{path}: no aligned samples of {excitation} and {response} "
                         f"({stats.received_excitation} and {stats.received_response} received)")
    sizes = np.cumsum([0] + [c[0].size for c in chunks])
    runs = Runs.from_lengths([sizes[stop] - sizes[start]
                              for start, stop in zip(segments, [*segments[1:], len(chunks)], strict=True)])
    if runs.count > 1:
        print(f"hammer-ros: {path}: {stats.gaps + stats.clock_resets} gap(s) in the streams: {runs.count} runs",
              file=sys.stderr)
    t, v, y = (np.concatenate(parts) for parts in zip(*chunks))
    return t, v, y, runs if runs.count > 1 else None


# ------------------------------------------------------------------------------- writing
def message_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of a type: its .msg text followed by every nested type's,
    each after a line of 80 '=' and ``MSG: pkg/Name`` (the layout rosbag2 writes)."""
    package, name = _split_type(type_name)
    parts, seen, order = {}, set(), []

    def visit(pkg: str, msg: str) -> None:
        key = f"{pkg}/{msg}"
        if key in seen:
            return
        seen.add(key)
        text = _msg_text(pkg, msg)
        parts[key] = text
        order.append(key)
        for dep_pkg, dep_msg in _dependencies(text, pkg):
            visit(dep_pkg, dep_msg)

    visit(package, name)
    text = parts[order[0]]
    for key in order[1:]:
        text += f"\n{SCHEMA_SEPARATOR}\nMSG: {key}\n{parts[key]}"
    return text


def _split_type(type_name: str) -> tuple[str, str]:
    parts = type_name.split("/")
    if len(parts) not in (2, 3) or (len(parts) == 3 and parts[1] != "msg"):
        raise UsageError(f"message type {type_name!r}: expected pkg/msg/Name")
    return parts[0], parts[-1]


def _msg_text(package: str, name: str) -> str:
    for root in (SCHEMA_DIR, Path(sys.prefix) / "share"):
        file = root / package / "msg" / f"{name}.msg"
        if file.is_file():
            return file.read_text()
    raise UsageError(f"message type {package}/msg/{name}: no .msg definition found")


def _dependencies(text: str, package: str) -> list[tuple[str, str]]:
    """The nested message types of a .msg text, as (package, name) (``cdr.definition_fields``:
    constants and primitive fields are skipped, a bare ``Name`` is in the same package)."""
    from ..ros.cdr import definition_fields, element_type

    bases = [element_type(t) for t in definition_fields(text, package).values()]
    return [(base.split("/")[0], base.split("/")[-1]) for base in bases if "/" in base]


def node_topic(topic: str, node_name: str = "hammer_ros") -> str:
    """'~/model' -> '/hammer_ros/model' (the private namespace of the node)."""
    return f"/{node_name}/{topic[2:]}" if topic.startswith("~/") else topic


def check_output_path(path: str | Path, option: str) -> Path:
    """A result file's path, checked before anything is written: a ``.mcap`` name in an existing,
    writable directory (UsageError naming ``option``)."""
    path = Path(path)
    if path.suffix.lower() != ".mcap":
        raise UsageError(f"{option}: {path}: the file name must end in .mcap")
    folder = path.parent
    if not folder.is_dir():
        raise UsageError(f"{option}: {path}: No such file or directory")
    if not os.access(folder, os.W_OK):
        raise UsageError(f"{option}: {path}: Permission denied")
    return path


def _create_mcap(path: str | Path, option: str):
    """(path, open binary file) of a new ``.mcap`` result file; UsageError naming ``option``."""
    path = check_output_path(path, option)
    try:
        return path, open(path, "wb")
    except OSError as exc:
        raise UsageError(f"{option}: {path}: {exc.strerror}") from None


class _McapFile:
    """The context manager of the result writers: the file is finished and closed on exit, also
    after an error."""

    _file: Any
    _writer: Any

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._writer.finish()
            finally:
                self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ResultWriter(_McapFile):
    """An MCAP file of ROS 2 messages given as dicts (``outputs`` form), nothing else: every
    message deserialises in a ROS 2 reader (rosbags, rosbag2) and in Foxglove."""

    def __init__(self, path: str | Path, option: str = "--out") -> None:
        from mcap_ros2.writer import Writer

        self.path, self._file = _create_mcap(path, option)
        self._writer = Writer(self._file)
        self._schemas: dict[str, Any] = {}
        self.count = 0

    def write(self, topic: str, type_name: str, message: dict, log_time_ns: int) -> None:
        schema = self._schemas.get(type_name)
        if schema is None:
            schema = self._schemas[type_name] = self._writer.register_msgdef(type_name,
                                                                             message_definition(type_name))
        self._writer.write_message(topic, schema, message, log_time=int(log_time_ns), publish_time=int(log_time_ns))
        self.count += 1


class JsonWriter(_McapFile):
    """An MCAP file of JSON messages, each channel with its JSON schema (message encoding
    ``json``, schema encoding ``jsonschema``: what Foxglove reads; the Foxglove dashboard
    channels of ``replay --dashboard-out``). Kept apart from the ROS 2 results, whose readers
    reject a JSON channel."""

    def __init__(self, path: str | Path, option: str = "--dashboard-out") -> None:
        from mcap.writer import Writer

        self.path, self._file = _create_mcap(path, option)
        self._writer = Writer(self._file)
        self._writer.start(profile="", library="hammer_ros")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.count = 0

    def write(self, topic: str, schema_name: str, schema: dict, message: dict, log_time_ns: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            schema_id = self._schemas.get(schema_name)
            if schema_id is None:
                schema_id = self._schemas[schema_name] = self._writer.register_schema(
                    schema_name, "jsonschema", json.dumps(schema).encode())
            channel = self._channels[topic] = self._writer.register_channel(topic, "json", schema_id)
        self._writer.add_message(channel, int(log_time_ns), json.dumps(message, allow_nan=False).encode(),
                                 int(log_time_ns))
        self.count += 1
