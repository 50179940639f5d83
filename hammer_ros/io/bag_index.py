"""What is in a bag, without decoding a message: its files (``bag_files``: a ``.mcap``/``.db3``
file or a rosbag2 directory, ``rosbag2``), each file's schemas, channels and message counts
(``file_index``: from the MCAP summary, else from a sequential, fault-tolerant scan of its
records, ``RecordScan``: a truncated or corrupt recording gives every valid record, and
``damage`` says where it broke), the bag's topics, counts and duration, what reading skipped
(``BagReadStats``) and the ``hammer-ros: warning:`` lines of a command (``WarningLog``: each
distinct text once; the command that reads owns it, so two commands, threads or ``hammer_ros.read``
calls in one process share none).
"""

from __future__ import annotations

import functools
import struct
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import UsageError
from ..messages.types import message_definition
from .rosbag2 import read_layout, readable_file, storage_of
from .rosbag2_sqlite import sqlite_index

MAX_RECORD_BYTES = 256 * 2**20  # an MCAP record (chunk) claiming more is treated as damage, never allocated
MAX_MESSAGE_BYTES = 16 * 2**20  # a message larger than this (2 M float64 samples) is skipped and counted
FIELD_CHECK_MESSAGES = 100  # a field path must work in one of the first messages of its topic


class WarningLog:
    """The ``hammer-ros: warning:`` lines of one command on stderr, each distinct text once (a command
    may read a bag more than once: its reference, a bag's several channels)."""

    def __init__(self) -> None:
        self.printed: set[str] = set()

    def warn(self, *texts: str) -> None:
        for text in texts:
            if text not in self.printed:
                self.printed.add(text)
                print(f"hammer-ros: warning: {text}", file=sys.stderr)


@dataclass
class BagReadStats:
    """What reading a bag skipped; nothing is dropped silently (``warnings`` says what and why)."""

    layout_notes: list[str] = field(default_factory=list)  # how the bag's files were found (``BagLayout.note``)
    damage: list[str] = field(default_factory=list)  # where a file is truncated or corrupt
    oversized: int = 0  # messages larger than MAX_MESSAGE_BYTES
    undecodable: int = 0  # messages whose CDR bytes do not decode with their schema
    field_errors: dict[str, int] = field(default_factory=dict)  # topic -> messages without the field
    first_error: dict[str, str] = field(default_factory=dict)  # kind or topic -> the first reason
    zero_stamps: dict[str, int] = field(default_factory=dict)  # topic -> messages whose header stamp is zero

    def note(self, key: str, reason: str) -> None:
        self.first_error.setdefault(key, reason)

    def warnings(self, path: str | Path) -> list[str]:
        lines = [*self.layout_notes, *self.damage]
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


def bag_files(path: str | Path) -> list[Path]:
    """The files of a bag in reading order: a .mcap/.db3 file, or a rosbag2 directory's."""
    return list(read_layout(path).files)


_last_chunk: tuple[tuple, list] | None = None  # the chunk parsed last and its records (``RecordScan._chunk``)
KEEP_CHUNK_BYTES = 16 * 2**20  # a larger chunk is not kept (a process that read a bag holds at most this)


class RecordScan:
    """A sequential, fault-tolerant read of one MCAP file (no summary needed, so an unfinished
    recording is read too). ``groups()`` yields the records of each chunk as one list (a record
    outside chunks as a list of one). A chunk that fails its CRC, decompression or parsing is
    skipped; a record that cannot be read ends the file (its length is unknown, nothing after it
    can be found). ``damage`` says where, in bytes from the start of the file. The chunk parsed
    last is kept (by file, offset, size and modification time), so that a read after the field
    checks, which parse the first chunk, does not parse it again (up to KEEP_CHUNK_BYTES)."""

    def __init__(self, file: Path) -> None:
        self.file = file
        self.damage: list[str] = []
        self.header_seen = False
        self.messages = 0  # message records read (chunks included)
        self._identity: tuple = ()  # (file, size, modification time) while ``groups`` reads

    def groups(self) -> Iterator[list[Any]]:
        from mcap.exceptions import McapError
        from mcap.records import Chunk, Header

        source = readable_file(self.file)
        stat = source.stat()
        size, self._identity = stat.st_size, (str(source), stat.st_size, stat.st_mtime_ns)
        with open(source, "rb") as fh:
            records = _scan_reader()(fh, emit_chunks=True, record_size_limit=MAX_RECORD_BYTES).records
            offset = 0
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except (McapError, ValueError, EOFError, OSError, struct.error) as exc:
                    truncated = isinstance(exc, (EOFError, struct.error)) or type(exc).__name__ == "EndOfFile"
                    what = ("truncated: the file ends inside the record" if truncated
                            else f"unreadable ({error_reason(exc)})")
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
        global _last_chunk
        if chunk.uncompressed_size > MAX_RECORD_BYTES:
            self.damage.append(f"chunk at byte {offset:,} claims {chunk.uncompressed_size:,} bytes; skipped")
            return []
        key, last = (*self._identity, offset), _last_chunk
        if last is not None and last[0] == key:
            return list(last[1])
        try:
            records = chunk_records(chunk)
        except Exception as exc:  # damaged data fails in many ways inside zstd/lz4/the parser
            self.damage.append(f"chunk at byte {offset:,} is corrupt ({error_reason(exc)}); skipped")
            return []
        _last_chunk = (key, records) if chunk.uncompressed_size <= KEEP_CHUNK_BYTES else None
        return list(records)


@functools.cache
def _scan_reader():
    """mcap's ``StreamReader`` that steps over the message index records unparsed: a scan reads
    every message in its chunk, and parsing the index takes two ``read8`` calls per message in
    Python (the x100 bench replay's reading process: ~18 ms of ~250 ms of CPU)."""
    from mcap.opcode import Opcode
    from mcap.stream_reader import StreamReader

    class ScanReader(StreamReader):
        def _read_record(self, opcode: int, length: int):
            if opcode == Opcode.MESSAGE_INDEX:
                self._stream.read(length)
                return None
            return super()._read_record(opcode, length)

    return ScanReader


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


def error_reason(exc: BaseException) -> str:
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
    scan = RecordScan(path)
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

