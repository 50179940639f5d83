"""Bags in, MCAP out: today's import path of the bag modules, kept while callers move to them.

``bag_config`` (the msg_config YAML, stream specs, channels), ``bag_index`` (a bag's files,
schemas, channels and counts; the fault-tolerant MCAP scan; warnings), ``bag_reader`` (decoding
and aligning samples), ``bag_writer`` (``ResultWriter``, ``JsonWriter``); the ``.msg`` definitions
are ``hammer_ros.messages.types``.
"""

from ..messages.outputs import node_topic
from ..messages.types import SCHEMA_DIR, SCHEMA_SEPARATOR, message_definition
from .bag_config import (
    OTHER_KEYS,
    TOPIC_KEYS,
    Channel,
    StreamSpec,
    config_channels,
    engine_config_from_params,
    load_msg_config,
    parse_stream_spec,
    single_channel_params,
    stream_spec,
    stream_specs,
)
from .bag_index import (
    FIELD_CHECK_MESSAGES,
    MAX_MESSAGE_BYTES,
    MAX_RECORD_BYTES,
    BagReadStats,
    FileIndex,
    WarningLog,
    bag_duration,
    bag_files,
    bag_message_counts,
    bag_topics,
    chunk_records,
    file_index,
)
from .bag_reader import (
    FLUSH_SAMPLES,
    MAX_RECORD_SAMPLES,
    BagSample,
    check_fields,
    check_topics,
    header_stamp_ns,
    iter_bag_messages,
    iter_bag_samples,
    iter_role_samples,
    load_bag_record,
)
from .bag_writer import JsonWriter, ResultWriter, check_output_path, record_results

__all__ = [
    "FIELD_CHECK_MESSAGES", "FLUSH_SAMPLES", "MAX_MESSAGE_BYTES", "MAX_RECORD_BYTES", "MAX_RECORD_SAMPLES",
    "OTHER_KEYS", "SCHEMA_DIR", "SCHEMA_SEPARATOR", "TOPIC_KEYS", "BagReadStats", "BagSample", "Channel",
    "FileIndex", "JsonWriter", "ResultWriter", "StreamSpec", "WarningLog", "bag_duration", "bag_files",
    "bag_message_counts", "bag_topics", "check_fields", "check_output_path", "check_topics", "chunk_records",
    "config_channels", "engine_config_from_params", "file_index", "header_stamp_ns",
    "iter_bag_messages", "iter_bag_samples", "iter_role_samples", "load_bag_record", "load_msg_config",
    "message_definition", "node_topic", "parse_stream_spec", "record_results", "single_channel_params",
    "stream_spec", "stream_specs",
]
