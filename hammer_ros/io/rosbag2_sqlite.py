"""rosbag2's SQLite storage (``.db3``) read with the stdlib ``sqlite3``, as MCAP records.

Tables: ``topics`` (id, name, type, serialization_format, offered_qos_profiles
[, type_description_hash]) and ``messages`` (id, topic_id, timestamp, data); from Iron on also
``message_definitions`` (topic_type, encoding, encoded_message_definition, ...), ``schema`` and
``metadata``. A topic becomes an MCAP ``Channel`` (id = topic id) with a ``Schema`` per type:
the stored ``ros2msg`` definition, else (Humble stores none) the ``.msg`` definition that
``definition`` gives, so the MCAP path's CDR decoders read both. The messages of the wanted
topics come from one query ordered by timestamp (rosbag2's ``timestamp_idx``), in batches.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterator
from contextlib import closing
from pathlib import Path
from typing import Any

from ..errors import UsageError

BATCH_ROWS = 20_000  # messages per group


def _connect(source: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"{source.resolve().as_uri()}?mode=ro", uri=True)


def _reason(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def sqlite_index(file: Path, source: Path, definition: Callable[[str], str]) -> tuple[
        dict[int, Any], dict[int, Any], dict[int, int], tuple[int, int] | None, tuple[str, ...]]:
    """(schemas, channels, message counts by channel id, (first, last) timestamp or None, damage)
    of the ``.db3`` file ``file`` (read from ``source``, its decompressed copy or itself).
    ``definition(type)``: a type's ``.msg`` definition, UsageError when unknown. A file that is
    not a rosbag2 SQLite database is a UsageError naming ``file``; a messages table damaged part
    way is counted up to the damage, which ``damage`` describes."""
    from mcap.records import Channel, Schema

    try:
        with closing(_connect(source)) as db:
            tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if not {"topics", "messages"} <= tables:
                raise UsageError(f"{file}: not a rosbag2 SQLite file (no topics and messages tables)")
            topics = db.execute("SELECT id, name, type, serialization_format FROM topics WHERE typeof(id) = "
                                "'integer' AND typeof(name) = 'text' AND typeof(type) = 'text'").fetchall()
            stored = {}
            if "message_definitions" in tables:
                stored = {name: text for name, encoding, text in db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions")
                    if encoding == "ros2msg" and isinstance(text, str) and text}
            counts, span, damage = _message_counts(db)
    except sqlite3.DatabaseError as exc:
        raise UsageError(f"{file}: not a readable rosbag2 SQLite file ({_reason(exc)})") from None
    schemas: dict[int, Any] = {}
    schema_ids: dict[str, int] = {}
    for type_name in sorted({t[2] for t in topics}):
        text = stored.get(type_name)
        if text is None:
            try:
                text = definition(type_name)
            except UsageError:
                text = ""  # no definition: ``_Decoders`` says so when the topic is read
        schema_id = schema_ids[type_name] = len(schemas) + 1
        schemas[schema_id] = Schema(id=schema_id, name=type_name, encoding="ros2msg", data=text.encode())
    channels = {topic_id: Channel(id=topic_id, schema_id=schema_ids[type_name], topic=name,
                                  message_encoding=str(serialization or ""), metadata={})
                for topic_id, name, type_name, serialization in topics}
    return schemas, channels, counts, span, damage


def _message_counts(db: sqlite3.Connection) -> tuple[dict[int, int], tuple[int, int] | None, tuple[str, ...]]:
    """(message rows by topic id, (first, last) timestamp, damage): one aggregate query and the
    ends of ``timestamp_idx``; when the table is damaged, its rows one by one up to the damage."""
    try:
        counts = dict(db.execute("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id").fetchall())
        span = db.execute("SELECT (SELECT MIN(timestamp) FROM messages), (SELECT MAX(timestamp) FROM messages)"
                          ).fetchone()
        return counts, span if all(type(end) is int for end in span) else None, ()
    except sqlite3.DatabaseError as exc:
        counts, stamps = {}, []
        try:
            for topic_id, stamp in db.execute("SELECT topic_id, timestamp FROM messages"):
                counts[topic_id] = counts.get(topic_id, 0) + 1
                stamps += [stamp] if type(stamp) is int else []
        except sqlite3.DatabaseError:
            pass
        return counts, (min(stamps), max(stamps)) if stamps else None, (
            f"messages table damaged ({_reason(exc)}); counted the {sum(counts.values())} messages before it",)


class SqliteScan:
    """The messages of ``channel_ids`` in one ``.db3`` file, in timestamp order: ``groups()``
    yields lists of MCAP ``Message`` records (sequence = the row id). An error of the database
    part way ends the read; ``damage`` says after how many messages, and how many rows had no
    integer timestamp or blob data (skipped)."""

    def __init__(self, file: Path, source: Path, channel_ids: list[int]) -> None:
        self.file, self.source, self.channel_ids = file, source, channel_ids
        self.damage: list[str] = []
        self.messages = 0

    def groups(self) -> Iterator[list[Any]]:
        from mcap.records import Message

        if not self.channel_ids:
            return
        marks = ", ".join("?" * len(self.channel_ids))
        query = (f"SELECT id, topic_id, timestamp, data FROM messages WHERE topic_id IN ({marks}) "
                 "ORDER BY timestamp")
        group: list[Any] = []
        malformed = 0
        try:
            with closing(_connect(self.source)) as db:
                for row_id, topic_id, stamp, data in db.execute(query, self.channel_ids):
                    if type(stamp) is not int or type(data) is not bytes:
                        malformed += 1
                        continue
                    group.append(Message(channel_id=topic_id, sequence=row_id, log_time=stamp, publish_time=stamp,
                                         data=data))
                    if len(group) == BATCH_ROWS:
                        self.messages += len(group)
                        yield group
                        group = []
        except sqlite3.DatabaseError as exc:
            self.damage.append(f"unreadable ({_reason(exc)}); read the {self.messages + len(group)} messages "
                               "before it")
        self.messages += len(group)
        if malformed:
            self.damage.append(f"{malformed} message row(s) without an integer timestamp and blob data skipped")
        if group:
            yield group
