"""Result files: ``ResultWriter`` (an MCAP file of ROS 2 messages given as ``messages.outputs``
dicts, written by the ``mcap_ros2`` writer with the ``.msg`` definitions shipped in
``hammer_ros/data/ros2_msgs`` (Jazzy's, see the README there), so Foxglove Studio, rosbag2 and
``rosbags`` can open the file and deserialise every message) and ``JsonWriter`` (the JSON
dashboard channels, with their JSON schemas, in a file of their own); ``record_results`` writes
one solve's messages into both.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..errors import UsageError
from ..messages.dashboard import CHANNELS, dashboard_messages, dashboard_topic
from ..messages.outputs import checked_ns, node_topic
from ..messages.types import message_definition


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


def record_results(writer: ResultWriter | None, messages: list[tuple[str, str, dict]], stamp_ns: int,
                   node_name: str, *, dashboard_writer: JsonWriter | None = None,
                   dashboard: list[tuple[str, dict]] | None = None) -> None:
    """Write ``messages`` (as ROS 2 messages) into ``writer`` and their dashboard channels (as
    JSON with their schemas; ``dashboard`` when already built) into ``dashboard_writer``, all at
    log time ``stamp_ns``."""
    stamp_ns = checked_ns(stamp_ns)
    if writer is not None:
        for topic, type_name, message in messages:
            writer.write(node_topic(topic, node_name), type_name, message, stamp_ns)
    if dashboard_writer is not None:
        for channel, message in dashboard if dashboard is not None else dashboard_messages(messages, stamp_ns):
            schema_name, schema = CHANNELS[channel]
            dashboard_writer.write(dashboard_topic(channel, node_name), schema_name, schema, message, stamp_ns)
