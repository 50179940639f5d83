"""MCAP bags in and out: ``.mcap`` files and rosbag2 directories (metadata.yaml + .mcap files).

Reading uses ``mcap`` + ``mcap_ros2`` (CDR decoding from the ``ros2msg`` schemas stored in the
bag, so no ROS installation is needed). Only the topics asked for are decoded; other topics and
unknown schemas are skipped. A sample's stamp is the message's ``header.stamp`` when it has a
header (an all-zero stamp counts as unset), else the bag's log time; a message with n samples
(``data[:]``, a numeric array field) follows the batch convention of ``field_path``.

Writing (``ResultWriter``) uses the ``mcap_ros2`` writer with the ``.msg`` definitions shipped in
``hammer_ros/data/ros2_msgs`` (Jazzy's, see the README there), so Foxglove Studio, rosbag2 and
``rosbags`` can open the file.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .data_io import Record
from .errors import UsageError
from .field_path import FieldPath, extract_samples, message_stamp, parse_field_path
from .streaming import EngineConfig, EngineStats, StreamAligner

SCHEMA_DIR = Path(__file__).resolve().parent / "data" / "ros2_msgs"
SCHEMA_SEPARATOR = "=" * 80
PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
              "int64", "uint64", "string", "wstring"}
# msg_config keys that are not engine settings
TOPIC_KEYS = ("excitation_topic", "excitation_type", "excitation_field", "response_topic", "response_type",
              "response_field")
OTHER_KEYS = ("solve_rate", "frame_id", "use_sim_time")
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
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise UsageError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
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
            value = tuple(float(c) for c in value) if value else None
        changes[key] = value
    try:
        config = EngineConfig(**{**(base or EngineConfig()).__dict__, **changes})
        return config.validated()
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{source}: {exc}") from None


def stream_specs(input_spec: str | None, output_spec: str | None, params: dict[str, Any] | None,
                 source: str = "config") -> tuple[StreamSpec, StreamSpec]:
    """(excitation, response) from --input/--output, falling back to the config's topics/fields."""
    params = params or {}
    specs = []
    for option, role, text in (("--input", "excitation", input_spec), ("--output", "response", output_spec)):
        if text:
            specs.append(parse_stream_spec(text, option))
            continue
        topic, field = params.get(f"{role}_topic"), params.get(f"{role}_field")
        if not topic or not field:
            raise UsageError(f"{option}: give /topic:field or a --config with {role}_topic and {role}_field")
        try:
            specs.append(StreamSpec(str(topic), parse_field_path(str(field)), params.get(f"{role}_type")))
        except UsageError as exc:
            raise UsageError(f"{source}: {role}_field: {exc}") from None
    return specs[0], specs[1]


# ------------------------------------------------------------------------------- reading
def bag_files(path: str | Path) -> list[Path]:
    """The .mcap files of a bag: the file itself, or those listed in a rosbag2 metadata.yaml."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such bag (expected a .mcap file or a rosbag2 directory)")
    if path.is_file():
        if path.suffix.lower() != ".mcap":
            raise UsageError(f"{path}: not a .mcap file")
        return [path]
    meta = path / "metadata.yaml"
    if not meta.is_file():
        raise UsageError(f"{path}: not a rosbag2 directory (no metadata.yaml)")
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        storage = info.get("storage_identifier", "mcap")
        files = [path / f for f in info.get("relative_file_paths", [])]
    except (yaml.YAMLError, KeyError, TypeError, AttributeError):
        raise UsageError(f"{meta}: not a rosbag2 metadata file") from None
    if storage != "mcap":
        raise UsageError(f"{path}: storage {storage!r} is not supported (record with -s mcap)")
    files = files or sorted(path.glob("*.mcap"))
    missing = [f for f in files if not f.is_file()]
    if not files or missing:
        raise UsageError(f"{path}: bag file {missing[0] if missing else '*.mcap'} is missing")
    return files


def _summaries(path: str | Path):
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    for file in bag_files(path):
        try:
            with open(file, "rb") as fh:
                summary = make_reader(fh).get_summary()
        except (McapError, OSError, ValueError, EOFError) as exc:
            raise UsageError(f"{file}: not a readable MCAP file ({exc})") from None
        if summary is None:
            raise UsageError(f"{file}: MCAP file without a summary (unfinished recording?)")
        yield summary


def bag_topics(path: str | Path) -> dict[str, str]:
    """topic -> ROS type name of every channel in the bag."""
    topics = {}
    for summary in _summaries(path):
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            topics[channel.topic] = schema.name if schema else ""
    return topics


def bag_message_counts(path: str | Path) -> dict[str, int]:
    """topic -> number of messages (from the MCAP summaries)."""
    counts: dict[str, int] = {}
    for summary in _summaries(path):
        per_channel = summary.statistics.channel_message_counts if summary.statistics else {}
        for channel_id, count in per_channel.items():
            topic = summary.channels[channel_id].topic
            counts[topic] = counts.get(topic, 0) + count
    return counts


def check_topics(path: str | Path, specs: tuple[StreamSpec, ...]) -> dict[str, str]:
    """The bag's topic types; a UsageError when a spec's topic is absent or of another type."""
    topics = bag_topics(path)
    for spec in specs:
        if spec.topic not in topics:
            raise UsageError(f"{path}: no topic {spec.topic!r} (topics: {', '.join(sorted(topics)) or 'none'})")
        wanted, found = _normal_type(spec.type_name), _normal_type(topics[spec.topic])
        if wanted and found and wanted != found:
            raise UsageError(f"{path}: topic {spec.topic} has type {topics[spec.topic]}, config says {spec.type_name}")
    return topics


def _normal_type(name: str | None) -> str:
    """'pkg/msg/Name' and 'pkg/Name' compare equal."""
    if not name:
        return ""
    parts = name.split("/")
    return f"{parts[0]}/{parts[-1]}"


def iter_bag_messages(path: str | Path, topics: list[str]) -> Iterator[tuple[str, int, Any]]:
    """(topic, log time in ns, decoded message) of ``topics`` in log-time order, over all files."""
    import heapq

    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    def one_file(file: Path):
        try:
            with open(file, "rb") as fh:
                reader = make_reader(fh, decoder_factories=[DecoderFactory()])
                for _, channel, message, decoded in reader.iter_decoded_messages(topics, log_time_order=True):
                    yield message.log_time, channel.topic, decoded
        except (McapError, OSError, EOFError, ValueError, KeyError) as exc:
            raise UsageError(f"{file}: cannot decode ({type(exc).__name__}: {exc})") from None

    for log_time, topic, decoded in heapq.merge(*(one_file(f) for f in bag_files(path)), key=lambda m: m[0]):
        yield topic, log_time, decoded


def check_fields(path: str | Path, specs: tuple[StreamSpec, ...]) -> None:
    """A UsageError when a spec's topic has no messages or its field is not in the first one."""
    counts = bag_message_counts(path)
    for spec in specs:
        if not counts.get(spec.topic):
            raise UsageError(f"{path}: topic {spec.topic} has no messages")
    pending = {spec.topic: [s for s in specs if s.topic == spec.topic] for spec in specs}
    for topic, _, msg in iter_bag_messages(path, list(pending)):
        for spec in pending.pop(topic, []):
            try:
                extract_samples(msg, spec.field)
            except UsageError as exc:
                raise UsageError(f"{path}: topic {topic}: {exc}") from None
        if not pending:
            return


@dataclass(frozen=True, eq=False)
class BagSample:
    """The samples one message contributes to a stream."""

    stream: str  # "excitation" or "response"
    stamp: float  # header stamp or log time (s): the time of the LAST sample
    values: np.ndarray
    log_time: int  # ns


def iter_bag_samples(path: str | Path, excitation: StreamSpec, response: StreamSpec) -> Iterator[BagSample]:
    """The excitation and response samples of the bag, message by message in log-time order.
    When both specs name the same topic, each message feeds both streams."""
    check_topics(path, (excitation, response))
    roles: dict[str, list[tuple[str, StreamSpec]]] = {}
    for role, spec in (("excitation", excitation), ("response", response)):
        roles.setdefault(spec.topic, []).append((role, spec))
    for topic, log_time, msg in iter_bag_messages(path, list(roles)):
        stamp = message_stamp(msg)
        stamp = log_time * 1e-9 if not stamp else stamp
        for role, spec in roles[topic]:
            try:
                values = extract_samples(msg, spec.field)
            except UsageError as exc:
                raise UsageError(f"{path}: topic {topic}: {exc}") from None
            yield BagSample(role, stamp, values, log_time)


def load_bag_record(path: str | Path, input_spec: str | None = None, output_spec: str | None = None,
                    config: str | Path | None = None) -> Record:
    """All aligned samples of a bag as a Record (the streaming engine's alignment, without the
    window): used by ``identify``/``diagnose`` on bags. Gaps are bridged by concatenating the
    gap-free segments (a note on stderr says how many)."""
    params = load_msg_config(config) if config else {}
    engine_config = engine_config_from_params(params, str(config or "config"))
    excitation, response = stream_specs(input_spec, output_spec, params, str(config or "config"))
    chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    stats = EngineStats(sample_rate=engine_config.sample_rate)
    aligner = StreamAligner(engine_config, stats, lambda t, v, y: chunks.append((t, v, y)), lambda: None)
    for sample in iter_bag_samples(path, excitation, response):
        aligner.add_message(sample.stream, sample.stamp, sample.values, flush=False)
        if aligner.buffered >= FLUSH_SAMPLES:
            aligner.flush()
    aligner.flush()
    if not chunks:
        raise UsageError(f"{path}: no aligned samples of {excitation} and {response} "
                         f"({stats.received_excitation} and {stats.received_response} received)")
    if stats.gaps:
        print(f"hammer-ros: {path}: {stats.gaps} gap(s) in the streams; segments concatenated", file=sys.stderr)
    t, v, y = (np.concatenate(parts) for parts in zip(*chunks))
    return Record(v, y, t, str(path))


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
    """The nested message types of a .msg text, as (package, name); constants (``byte OK=0``)
    and primitive fields are skipped, a bare ``Name`` is in the same package."""
    deps = []
    for line in text.splitlines():
        tokens = line.split("#", 1)[0].split()
        if len(tokens) < 2 or "=" in line.split("#", 1)[0]:
            continue
        base = re.sub(r"(<=\d+)?(\[[^\]]*\])?$", "", tokens[0])
        if base in PRIMITIVES:
            continue
        pkg, _, msg = base.rpartition("/")
        deps.append((pkg.split("/")[0] if pkg else package, msg))
    return deps


def node_topic(topic: str, node_name: str = "hammer_ros") -> str:
    """'~/model' -> '/hammer_ros/model' (the private namespace of the node)."""
    return f"/{node_name}/{topic[2:]}" if topic.startswith("~/") else topic


class ResultWriter:
    """An MCAP file of ROS 2 messages given as dicts (``outputs`` form); use as a context manager
    (the file is finished and closed on exit, also after an error)."""

    def __init__(self, path: str | Path) -> None:
        from mcap_ros2.writer import Writer

        self.path = Path(path)
        if self.path.suffix.lower() != ".mcap":
            raise UsageError(f"--out: {self.path}: the file name must end in .mcap")
        try:
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise UsageError(f"--out: {self.path}: {exc.strerror}") from None
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

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._writer.finish()
            finally:
                self._file.close()

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
