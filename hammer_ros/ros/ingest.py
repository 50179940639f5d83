"""A channel's ingestion: its inputs, its ``ArrivalStamper`` and the move of the queued messages
into its engine (``Ingest.flush``, in the channel's ingest thread, under the channel's lock).

Stamps: a message with a non-zero ``header.stamp`` is placed by its stamp (a batch of n samples
holds samples at stamp - (n-1)/fs .. stamp); any other message is placed by counting samples at
the sample rate, anchored on the least delayed receive times (``sample_clock.ArrivalStamper``),
except a message whose header stamp is zero (no stamp) on a stream that publishes far below the
grid rate (a setpoint: its median arrival interval over the last ``ARRIVALS`` messages longer than
``HOLD_PERIODS`` sample periods per sample): counting would put its samples a period apart, so it
is placed at its receive time, read on the other stream's time base (``_place_by_arrival``), and
the aligner holds it until the next one. The first zero stamp of a topic is logged once.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from .environment import prepare_ros_environment

prepare_ros_environment()

from rclpy.qos import QoSProfile, qos_profile_sensor_data  # noqa: E402

from ..messages.cdr import extract_batch  # noqa: E402
from ..messages.field_path import FieldError, parse_field_path  # noqa: E402
from ..streaming.config import HOLD_PERIODS  # noqa: E402
from ..streaming.engine import StreamingEngine  # noqa: E402
from ..streaming.sample_clock import ArrivalStamper  # noqa: E402
from .inputs import _drained, _Input, built_reader  # noqa: E402
from .message_types import input_message_class as message_class  # noqa: E402
from .message_types import raw_extractor  # noqa: E402
from .parameters import REFERENCE, STREAMS  # noqa: E402


class Ingest:
    """The inputs (excitation, response, reference) of one channel, the stamper that places their
    samples and the count of samples it could not place (``unplaced``). ``values``: the channel's
    parameter values (topics, types, fields, max_pending, qos_depth), replaced when they change."""

    def __init__(self, values: dict[str, Any], logger) -> None:
        self.values = values
        self.logger = logger
        self.inputs = {s: _Input(s) for s in (*STREAMS, REFERENCE)}
        self.stamper = ArrivalStamper(values["sample_rate"])
        self.unplaced = 0  # samples seen while the stamper still infers the rate

    def restart(self) -> None:
        """Forget the queued messages and the stamper's clock (``~/reset``)."""
        for source in self.inputs.values():
            source.pending.clear()
        self.stamper = ArrivalStamper(self.values["sample_rate"])

    def prepare(self, stream: str) -> tuple[_Input, Any, QoSProfile]:
        """The input of ``stream`` made ready to read its messages: (input, message class, QoS)."""
        source = self.inputs[stream]
        cls = message_class(self.values[f"{stream}_type"])
        source.headed = cls.get_fields_and_field_types().get("header") == "std_msgs/Header"
        source.path = parse_field_path(self.values[f"{stream}_field"])
        source.raw = raw_extractor(cls, source.path)  # None: rclpy builds the messages
        source.read = source.raw or built_reader(source.path)
        qos = QoSProfile(depth=self.values["qos_depth"], reliability=qos_profile_sensor_data.reliability,
                         durability=qos_profile_sensor_data.durability, history=qos_profile_sensor_data.history)
        source.pending_limit = max(1, self.values["max_pending"] // source.message_samples)
        return source, cls, qos

    def _bad_message(self, stream: str, exc: Exception) -> None:
        self._bad_messages(stream, 1, str(exc) if isinstance(exc, FieldError) else f"{type(exc).__name__}: {exc}")

    def _bad_messages(self, stream: str, count: int, why: str) -> None:
        """``count`` messages of ``stream`` skipped, the last for ``why``: counted, warned (throttled)."""
        source = self.inputs[stream]
        source.field_errors += count
        source.last_error = why
        self.logger.warning(f"{stream} {self.values[f'{stream}_topic']}: {why}", throttle_duration_sec=5.0)

    def distribute(self) -> None:
        """Decode the shared topics' queued messages for every channel reading them (several readers)."""
        for source in self.inputs.values():
            if source.feed is not None:
                source.feed.distribute()

    def flush(self, engine: StreamingEngine) -> None:
        """Move the queued samples into the engine: one vectorised add of both streams,
        interleaved in time (``StreamingEngine.add_streams``)."""
        self.distribute()
        pending = {stream: _drained(source.pending) for stream, source in self.inputs.items()}
        batches = {stream: (self._decoded(stream, items) if self.inputs[stream].feed
                             else self._stamped(engine, stream, items))
                   for stream, items in pending.items() if items}
        reference = batches.pop(REFERENCE, None)
        if reference is not None:
            engine.add_reference(*reference)
        self._place_by_arrival(batches)
        engine.add_streams({k: v for k, v in batches.items() if v is not None})
        for source in self.inputs.values():
            source.pending_limit = max(1, self.values["max_pending"] // source.message_samples)

    def _stamped(self, engine: StreamingEngine, stream: str,
                 items: list[tuple[float, Any, Callable]]) -> tuple | None:
        """(stamps, values) of one stream's queued messages (None when none could be placed): each
        message's samples read (a bad one counted and skipped), then per message only its first
        stamp found; the stamps of all samples are made at once, ``first + k / fs`` for the k-th
        sample of each message. Messages of one layout without a header stamp: ``_counted``."""
        receives, messages, reads = zip(*items)
        read = reads[0]  # serialized messages of one layout, all from one subscription: read at once
        block = extract_batch(read, list(messages)) if reads.count(read) == len(reads) else None
        if block is not None:
            return self._counted(stream, receives, block)
        firsts: list[float] = []
        sizes: list[int] = []
        values: list = []
        arrived: list[float] = []
        explicit: list[tuple[int, np.ndarray]] = []  # stamped batches placed by the engine's rule
        total = 0
        source = self.inputs[stream]
        for receive, msg, read in items:
            try:
                x, stamp = read(msg)
            except Exception as exc:  # FieldError, or anything odd in a message: counted, never fatal
                self._bad_message(stream, exc)
                continue
            n = source.message_samples = 1 if type(x) is float else x.size
            if n == 0:
                continue
            if stamp and n == 1:
                first = stamp
            elif stamp:  # a stamped batch: the last sample at the stamp
                t = (engine.message_stamps(stream, stamp, n) if stream != REFERENCE else
                     stamp - np.arange(n - 1, -1, -1) / self.stamper.rate if self.stamper.rate else None)
                if t is None:
                    engine.stats.unstamped += 1
                    continue
                explicit.append((total, t))
                first = t[0]
            elif source.headed and self._sparse(stream, receive, n):
                source.by_arrival.append((total, n, receive))
                first = math.nan  # placed at the end of the flush (``_place_by_arrival``)
            else:
                first = self.stamper.first_stamp(stream, receive, n)
                if first is None:
                    self.unplaced += n
                    continue
            firsts.append(first)
            sizes.append(n)
            values.append(x)
            arrived.append(receive)
            total += n
        if not values:
            return None
        floats = [type(x) is float for x in values]
        counts = np.array(sizes)
        if all(floats):  # single samples
            stamps, joined = np.array(firsts), np.array(values)
        else:
            offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)  # k within its message
            # (fs is known whenever a batch was placed by counting; explicit stamps overwrite theirs)
            stamps = np.repeat(np.array(firsts), counts) + offsets / (self.stamper.rate or 1.0)
            for start, t in explicit:
                stamps[start:start + t.size] = t
            joined = np.concatenate([np.atleast_1d(x) for x in values] if any(floats) else values)
        ends = stamps[np.cumsum(counts) - 1]
        placed = np.isfinite(ends)
        if placed.any():
            source.arrival_map = (np.array(arrived)[placed], ends[placed])
        return stamps, joined

    def _sparse(self, stream: str, receive: float, samples: int) -> bool:
        """Whether ``stream``, whose message received at ``receive`` has a zero header stamp,
        publishes far below the grid rate (module docstring), or is not yet known not to (its first
        message); counts and logs the zero stamp."""
        source = self.inputs[stream]
        if not source.zero_stamps:
            self.logger.warning(f"{stream} {self.values[f'{stream}_topic']}: header.stamp is zero (no stamp): "
                                      "its samples are placed by their receive times")
        source.zero_stamps += 1
        source.arrivals.append(receive)
        if stream == REFERENCE or (not self.stamper.rate and samples > 1):
            return False
        if len(source.arrivals) < 2 or not self.stamper.rate:  # not yet known: never counted on a wrong clock
            return True
        interval = float(np.median(np.diff(source.arrivals)))
        return interval > HOLD_PERIODS * samples / self.stamper.rate

    def _place_by_arrival(self, batches: dict[str, tuple | None]) -> None:
        """Stamp the samples left for it by ``_stamped`` (zero-stamped messages of a sparse
        stream): the message's receive time r read on the other stream's stamps, s_j + (r - r_j)
        for the other stream's message j received nearest to r (its receive time r_j, its last
        sample's stamp s_j): whatever that stream's time base (a robot's clock, a bag's recording
        time played at any rate, or receive times) the message lands where the other stream was
        when it arrived. Before the other stream's first message it cannot be placed (unplaced)."""
        for stream, other in (STREAMS, STREAMS[::-1]):
            source = self.inputs[stream]
            if not source.by_arrival or batches.get(stream) is None:
                source.by_arrival.clear()
                continue
            stamps, values = batches[stream]
            receives, ends = self.inputs[other].arrival_map
            for start, n, receive in source.by_arrival:
                if receives.size:
                    j = int(np.argmin(np.abs(receives - receive)))
                    last = ends[j] + receive - receives[j]
                    stamps[start:start + n] = last - np.arange(n - 1, -1, -1) / (self.stamper.rate or 1.0)
                else:
                    self.unplaced += n
            source.by_arrival.clear()
            placed = np.isfinite(stamps)
            if not placed.all():
                batches[stream] = (stamps[placed], values[placed]) if placed.any() else None

    def _decoded(self, stream: str, chunks: list[tuple]) -> tuple | None:
        """``_stamped`` for the chunks of a shared topic (``SharedTopic.distribute``: receive
        times, values, bad, header stamps, why bad), one number per message: a bad one counted
        and skipped, a message with a stamp at its stamp, the others stamped by the stamper."""
        receives, values, bad, stamps = (np.concatenate(column) for column in list(zip(*chunks))[:4])
        if bad.any():
            self._bad_messages(stream, int(np.count_nonzero(bad)), next(c[4] for c in reversed(chunks) if c[2].any()))
            good = ~bad
            receives, values, stamps = receives[good], values[good], stamps[good]
        self.inputs[stream].message_samples = 1
        unstamped = stamps == 0.0
        if unstamped.any():
            stamps[unstamped] = self.stamper.first_stamps(stream, receives[unstamped], 1)
        placed = np.isfinite(stamps)
        self.unplaced += placed.size - int(np.count_nonzero(placed))
        return (stamps[placed], values[placed]) if placed.any() else None

    def _counted(self, stream: str, receives: tuple[float, ...], block: np.ndarray) -> tuple | None:
        """``_stamped`` for messages of one layout without a header stamp (``extract_batch``'s
        block, a row per message): the stamper counts the first samples of all of them at once."""
        n = self.inputs[stream].message_samples = block.shape[1]
        if n == 0:
            return None
        firsts = self.stamper.first_stamps(stream, np.array(receives), n)
        placed = np.isfinite(firsts)
        self.unplaced += n * (placed.size - int(np.count_nonzero(placed)))
        if not placed.any():
            return None
        self.inputs[stream].arrival_map = (np.array(receives)[placed], firsts[placed] + (n - 1) / self.stamper.rate)
        return (firsts[placed, None] + np.arange(n) / self.stamper.rate).ravel(), block[placed].ravel()
