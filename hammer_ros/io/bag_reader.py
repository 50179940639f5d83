"""Samples out of a bag: its topics checked (``check_topics``, ``check_fields``), the messages
of the asked topics decoded with the CDR decoders built from the ``ros2msg`` schemas stored in
the bag (``mcap_ros2``: no ROS installation needed; other topics and unknown schemas are
skipped), a field's samples read (``field_path``; raw CDR reads by ``messages.cdr.schema_extractor``
where the layout allows), and the (excitation, response) pairs aligned into a record
(``load_bag_record``, ``iter_bag_samples``, ``iter_role_samples``).
A sample's stamp is the message's ``header.stamp`` when it has a header (an all-zero stamp is
no stamp: a warning names the topic once), else the bag's log time; a message with n samples
(``data[:]``, a numeric array field) follows the batch convention of ``field_path``.
Oversized or undecodable messages are skipped and counted (``bag_index.BagReadStats``).
"""

from __future__ import annotations

import contextlib
import io
import struct
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import UsageError
from ..identification.runs import Runs
from ..messages.field_path import extract_samples, message_stamp, message_stamp_ns
from ..messages.types import normal_type
from ..streaming.aligner import StreamAligner
from ..streaming.config import EngineConfig, EngineStats
from .bag_config import (
    StreamSpec,
    engine_config_from_params,
    load_msg_config,
    single_channel_params,
    stream_spec,
    stream_specs,
)
from .bag_index import (
    FIELD_CHECK_MESSAGES,
    MAX_MESSAGE_BYTES,
    BagReadStats,
    FileIndex,
    RecordScan,
    WarningLog,
    bag_files,
    bag_message_counts,
    bag_topics,
    error_reason,
    file_index,
)
from .records import Record
from .rosbag2 import decompress_message, read_layout, readable_file, storage_of
from .rosbag2_sqlite import SqliteScan

FLUSH_SAMPLES = 20_000  # buffered samples per vectorised engine update
MAX_RECORD_SAMPLES = 10_000_000  # identify/diagnose hold the aligned record in memory: at most this many samples


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
        wanted, found = normal_type(spec.type_name), normal_type(topics[spec.topic])
        if wanted and found and wanted != found:
            raise UsageError(f"{path}: topic {spec.topic} has type {topics[spec.topic]}, config says {spec.type_name}")
    wanted_topics = {spec.topic for spec in specs}
    for file in bag_files(path):
        decoders = _Decoders(file_index(file))
        for channel in decoders.index.channels.values():
            if channel.topic in wanted_topics:
                decoders.get(channel)
    return topics



DECODER_CACHE_SIZE = 64  # schemas whose decoders are kept across files and calls (``_Decoders``)
_schema_decoders: dict[tuple, Any] = {}
_schema_decoders_lock = threading.Lock()  # ``hammer_ros.read`` may run in several threads


class _Decoders:
    """CDR decoders of one file's channels, built from the ros2msg schemas stored in the bag. A
    decoder depends on its schema's text alone, so one built for a schema is reused for the same
    text in any file and call (the topic checks, the field checks and the read of every bag of a
    fleet parse each type once, not once per bag and pass: ~1 ms of a 20 ms fleet bag)."""

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
        key = (channel.message_encoding, schema.name, schema.encoding, bytes(schema.data))
        decoder = _schema_decoders.get(key)
        if decoder is None:
            try:
                with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                    decoder = self._factory.decoder_for(channel.message_encoding, schema)  # (the parser prints)
            except Exception as exc:  # the schema text comes from the file: any parse failure
                raise UsageError(f"{where}: cannot parse its schema {schema.name!r} ({error_reason(exc)})") from None
            if decoder is None:
                raise UsageError(f"{where}: {channel.message_encoding!r} messages with a {schema.encoding!r} schema "
                                 "are not ROS 2 CDR/ros2msg, cannot decode")
            with _schema_decoders_lock:
                while len(_schema_decoders) >= DECODER_CACHE_SIZE:
                    _schema_decoders.pop(next(iter(_schema_decoders)))
                _schema_decoders[key] = decoder
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
        stats.note("undecodable", f"{channel.topic}: {error_reason(exc)}")
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
    layout = read_layout(path)
    if layout.note and layout.note not in stats.layout_notes:
        stats.layout_notes.append(layout.note)

    def one_file(file: Path):
        decoders = _Decoders(file_index(file))
        scan = RecordScan(file) if storage_of(file) == "mcap" else SqliteScan(
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
    from ..messages.cdr import schema_extractor

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
    on the common grid these are its own samples). Warnings: each distinct one once per call, on stderr."""
    log = WarningLog()
    params = load_msg_config(config) if config else {}
    params = single_channel_params(params, str(config), "identify and diagnose read one pair (--input/--output, "
                                   "or replay for every channel)")
    engine_config = engine_config_from_params(params, str(config or "config"))
    excitation, response = stream_specs(input_spec, output_spec, params, str(config or "config"))
    reference = stream_spec("--reference", "reference", reference_spec, params, str(config or "config"),
                            required=False)
    t, v, y, runs = _aligned_samples(path, excitation, response, engine_config, log)
    if reference is None:
        return Record(v, y, t, str(path), runs=runs)
    try:
        t_r, _, r, _ = _aligned_samples(path, excitation, reference, engine_config, log)
    except UsageError as exc:
        raise UsageError(f"--reference: {exc}") from None
    return Record(v, y, t, str(path), np.interp(t, t_r, r), runs)


def _aligned_samples(path: str | Path, excitation: StreamSpec, response: StreamSpec, engine_config: EngineConfig,
                     log: WarningLog) -> tuple[np.ndarray, np.ndarray, np.ndarray, Runs | None]:
    """(t, v, y, runs): every aligned sample of the two streams and its gap-free segments as
    runs (None: one segment) (``load_bag_record``); what reading skipped warned in ``log``."""
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
    log.warn(*read.warnings(path))
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

