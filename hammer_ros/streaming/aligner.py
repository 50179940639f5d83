"""Steps 1-3 of the engine (``hammer_ros.streaming.engine``): screening, sample-rate inference, alignment of
the two streams on one grid, and the gap policy.

A *held* excitation: a command or setpoint stream published far below the grid rate (its median
step over more than ``HOLD_PERIODS`` grid periods, e.g. a 1 Hz setpoint beside a 100 Hz sensor)
holds each value until its next message (zero-order hold), as a controller holds its setpoint.
Then the grid is clocked by the response (its stamps, its inferred rate, or ``sample_rate``
anchored on it), and only a silence of the response is a gap, or a silence of the excitation
longer than a ``max_gap`` set explicitly; a held excitation is never interpolated (a set point does
not ramp between its messages). A response slower than the grid (``SPARSE_RESPONSE``) is interpolated
linearly. An excitation at about the grid rate is aligned as before: the grid is clocked by it and a
silence of either stream over ``max_gap`` is a gap."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from .config import (
    CLOCK_RESET_SECONDS,
    GRID_TOLERANCE,
    HOLD_PERIODS,
    INFER_SAMPLES,
    MAX_ABS_SAMPLE,
    PENDING_SAMPLES,
    SPARSE_RESPONSE,
    STREAMS,
    EngineConfig,
    EngineStats,
)


class _Stream:
    """Accepted samples of one stream not yet consumed by the grid (plus the one before).
    Appends are kept as parts and joined when the grid needs them, so a stream that runs far
    ahead of the other one costs O(samples), not O(samples x appends)."""

    def __init__(self) -> None:
        self._parts: list[tuple[np.ndarray, np.ndarray]] = []
        self.size = 0
        self.last = -np.inf
        self.previous_message: float | None = None
        self.jumped: list[tuple[np.ndarray, np.ndarray]] = []  # samples since this stream's stamps jumped back

    def _joined(self) -> tuple[np.ndarray, np.ndarray]:
        if len(self._parts) != 1:
            joined = (np.concatenate([p[0] for p in self._parts]) if self._parts else np.empty(0),
                      np.concatenate([p[1] for p in self._parts]) if self._parts else np.empty(0))
            self._parts = [joined]
        return self._parts[0]

    @property
    def t(self) -> np.ndarray:
        return self._joined()[0]

    @property
    def x(self) -> np.ndarray:
        return self._joined()[1]

    def append(self, t: np.ndarray, x: np.ndarray, cap: int) -> int:
        """Add accepted samples; beyond ``cap`` pending samples the oldest are dropped (returned)."""
        if t.size:
            self._parts.append((t, x))
            self.size += t.size
            self.last = float(t[-1])
        dropped = max(0, self.size - cap)
        if dropped:
            self.drop(dropped)
        return dropped

    def drop(self, count: int) -> None:
        t, x = self._joined()
        self._parts = [(t[count:], x[count:])]
        self.size = t.size - min(count, t.size)

    def clear(self) -> None:
        self._parts, self.size = [], 0

    def segment_end(self, index: int, max_gap: float, hold: float = 0.0) -> tuple[float, float | None]:
        """(stamp where the segment holding sample ``index`` ends, stamp of the first sample after
        the gap that ends it, or None while the segment is still open). ``hold``: how long the
        last sample before a gap (or the newest one) still holds (0: it ends the segment)."""
        t = self.t
        steps = t[index + 1 :] - t[index:-1]
        if steps.size == 0 or steps.max() <= max_gap:
            return float(t[-1]) + hold, None
        j = index + int(np.argmax(steps > max_gap))
        return float(t[j]) + hold, float(t[j + 1])

    def median_step(self) -> float:
        """Median step of the first INFER_SAMPLES stamps held (inf with fewer than two)."""
        t = self.t[:INFER_SAMPLES]
        return float(np.median(np.diff(t))) if t.size >= 2 else math.inf

    def values_at(self, grid: np.ndarray, tol: float, interpolation: str, start: int) -> np.ndarray:
        """The stream's values at the grid points (``start``: the index of the last sample at or before
        grid[0] + tol, -1 for none). Zero-order hold: the last sample at or before each point + tol;
        when the stream has exactly one sample in each grid interval, at any phase (a stream at the
        grid rate, e.g. stamped from its own arrivals), that is the run of samples from ``start``,
        checked by two comparisons instead of a search per point."""
        if interpolation == "linear":
            return np.interp(grid, self.t, self.x)
        t, x = self.t, self.x
        limit = grid + tol
        held, after = t[max(start, 0) : start + grid.size], t[start + 1 : start + grid.size + 1]
        if start >= 0 and held.size == grid.size and (held <= limit).all() and (after > limit[: after.size]).all():
            return x[start : start + grid.size]  # one sample per grid interval (any phase): the hold is the samples
        return x[np.searchsorted(t, limit, side="right") - 1]



class StreamAligner:
    """Screening, sample-rate inference, grid alignment and gap detection of the two streams
    (steps 1-3 of the module docstring). Aligned runs go to ``sink(grid, v, y)``; ``restart()``
    is called when a gap ends the current gap-free segment. Counters go to ``stats``."""

    def __init__(self, config: EngineConfig, stats: EngineStats,
                 sink: Callable[[np.ndarray, np.ndarray, np.ndarray], None], restart: Callable[[], None]) -> None:
        self.config, self.stats, self._sink, self._restart = config, stats, sink, restart
        self._streams = {s: _Stream() for s in STREAMS}
        self._buffer: dict[str, tuple[list, list]] = {s: ([], []) for s in STREAMS}
        self.buffered = 0
        self.rate: float | None = config.sample_rate or None
        self.held: bool | None = None  # the excitation is held (see the module docstring); None: not yet known
        self.sparse_response: bool | None = None  # the response is slower than the grid (interpolated linearly)
        self._anchor: float | None = None
        self._k = 0
        self._last_grid = -np.inf
        self._segment_samples = 0
        self._offsets: tuple[int, float, np.ndarray] = (0, 0.0, np.empty(0))  # message_stamps' last (count, period)

    def regrid(self, config: EngineConfig) -> None:
        """A new sample_rate: the grid restarts at the next excitation sample (0 = keep the old
        rate as the estimate behind the tolerances)."""
        self.config = config
        self.rate = config.sample_rate or self.rate
        self.stats.sample_rate = self.rate or 0.0
        self.held = self.sparse_response = None
        self._anchor = None
        self._segment_samples = 0
        self._emit()

    def message_stamps(self, stream: str, stamp: float, count: int) -> np.ndarray | None:
        """Stamps of the ``count`` samples of one message stamped ``stamp`` (batch convention:
        the last sample at the stamp, spacing 1/fs). While fs is unknown the spacing is taken
        from the previous message of the stream; the first such message gives None."""
        previous = self._streams[stream].previous_message
        self._streams[stream].previous_message = stamp
        if count <= 1:
            return np.full(count, float(stamp))
        if self.rate:
            period = 1.0 / self.rate
        elif previous is not None and stamp > previous:
            period = (stamp - previous) / count
        else:
            return None
        if self._offsets[:2] != (count, period):  # messages of one size at one rate: the offsets once
            self._offsets = (count, period, period * np.arange(count - 1, -1, -1))
        return stamp - self._offsets[2]

    def add_message(self, stream: str, stamp: float, values: np.ndarray, flush: bool = True) -> int:
        """Add one message's samples (batch convention of ``message_stamps``); returns how many
        were accepted. With ``flush=False`` the stamped samples are buffered until ``flush()``
        (one vectorised update for many messages; returns the number buffered)."""
        values = np.asarray(values, dtype=float).ravel()
        stamps = self.message_stamps(stream, stamp, values.size)
        if stamps is None:
            self.stats.unstamped += 1
            self._count_received(stream, values.size)
            return 0
        if not flush:
            self._buffer[stream][0].append(stamps)
            self._buffer[stream][1].append(values)
            self.buffered += values.size
            return values.size
        return self.add(stream, stamps, values)

    def flush(self) -> int:
        """Add the buffered messages of both streams (interleaved in time, see ``add_both``);
        returns how many samples were accepted."""
        batches = {}
        for stream, (stamps, values) in self._buffer.items():
            if stamps:
                batches[stream] = (np.concatenate(stamps), np.concatenate(values))
                stamps.clear()
                values.clear()
        self.buffered = 0
        return self.add_both(batches)

    @property
    def pending_cap(self) -> int:
        """Samples of one stream held while waiting for the other (older ones are dropped: ``overflow``)."""
        return max(4 * self.config.window, PENDING_SAMPLES)

    def add_both(self, batches: dict[str, tuple[np.ndarray, np.ndarray]]) -> int:
        """Add (stamps, values) of both streams in pieces of at most pending_cap / 4 samples,
        always continuing the stream that is behind in time, so that a long batch of one stream
        (e.g. a 10^6-element array message) is aligned as it goes instead of overflowing the
        pending buffer while the other stream's batch waits. The grid is emitted once a piece's
        worth of samples has been added since the last time, and at the end (so once for a flush
        of both streams). Returns the samples accepted."""
        piece = self.pending_cap // 4
        heads = {name: 0 for name in batches}
        accepted = added = 0
        while heads:
            def behind(name: str) -> float:
                t = batches[name][0]
                return float(t[heads[name]]) if np.isfinite(t[heads[name]]) else -np.inf

            name = min(heads, key=behind)
            t, x = batches[name]
            start = heads[name]
            stop = min(t.size, start + piece)
            accepted += self.add(name, t[start:stop], x[start:stop], emit=False)
            added += stop - start
            if stop >= t.size:
                del heads[name]
            else:
                heads[name] = stop
            if added >= piece or not heads:
                self._emit()
                added = 0
        return accepted

    def _count_received(self, stream: str, n: int) -> None:
        if stream == "excitation":
            self.stats.received_excitation += n
        else:
            self.stats.received_response += n

    def add(self, stream: str, t, x, emit: bool = True) -> int:
        """Screen and add samples x at stamps t (s) to ``stream``; returns how many were accepted.
        ``emit``: align what both streams hold now (else the caller does, ``add_both``)."""
        t = np.atleast_1d(np.asarray(t, dtype=float)).ravel()
        x = np.atleast_1d(np.asarray(x, dtype=float)).ravel()
        if t.size != x.size:
            raise ValueError(f"{stream}: {t.size} stamps for {x.size} samples")
        self._count_received(stream, x.size)
        finite = np.isfinite(t) & (np.abs(x) <= MAX_ABS_SAMPLE)  # False for NaN and inf too (comparisons never warn)
        kept = int(np.count_nonzero(finite))
        if kept < x.size:
            self.stats.nan_skipped += x.size - kept
            self.stats.bad_values[stream] += int(np.count_nonzero(~finite & np.isfinite(t)))
            t, x = t[finite], x[finite]
        accepted = self._add_screened(stream, t, x)
        if emit:
            self._emit()
        return accepted

    def _add_screened(self, stream: str, t: np.ndarray, x: np.ndarray) -> int:
        """Clock-jump handling: samples more than the reset threshold older than the stream's
        newest stamp are held (``jumped``) until the other stream jumps back too (then both
        restart there: ``clock_resets``) or this one goes on past its newest stamp (then they
        were a re-sent stretch: ``late``)."""
        s = self._streams[stream]
        if t.size == 0:
            return 0
        if s.jumped and t[0] > s.last:
            self._drop_jumped(s)
        if not s.jumped and t[0] > s.last and (t[1:] > t[:-1]).all():  # in order: all new
            return self._append(stream, t, x)
        newest = np.maximum.accumulate(np.concatenate([[s.last], t]))[:-1]
        back = np.flatnonzero(t < newest - self._reset_threshold())
        if back.size == 0 and not s.jumped:
            return self._accept(stream, t, x, newest)
        j = int(back[0]) if back.size else 0
        accepted = self._accept(stream, t[:j], x[:j], newest[:j])
        s.jumped.append((t[j:], x[j:]))
        held = sum(part.size for part, _ in s.jumped)
        while held > self.pending_cap:  # bounded: the oldest held samples go first
            held -= s.jumped[0][0].size
            self.stats.late += s.jumped.pop(0)[0].size
        other = self._streams[STREAMS[1 - STREAMS.index(stream)]]
        if other.jumped:  # both clocks went back (sim time reset, bag loop): restart on the new timeline
            self._emit()  # what came before the jump, on the old one
            self._reset_clock()
            return accepted + self._accept_jumped()
        return accepted

    def _reset_threshold(self) -> float:
        gap = self.config.max_gap or (5.0 / self.rate if self.rate else 0.0)
        return max(CLOCK_RESET_SECONDS, gap)

    def _drop_jumped(self, s: _Stream) -> None:
        self.stats.late += sum(t.size for t, _ in s.jumped)
        s.jumped.clear()

    def _reset_clock(self) -> None:
        """Both streams jumped back by more than the reset threshold (a re-sent stretch of one
        stream is only ``late``): restart the alignment of both streams (the window restarts as
        after a gap) with the samples since their jumps."""
        self.stats.clock_resets += 1
        self.stats.aligned_before_reset = self.stats.aligned
        for name, s in self._streams.items():
            s.clear()
            s.last = -np.inf
            self.stats.first_stamp.pop(name, None)
            self.stats.accepted[name] = self.stats.bad_values[name] = 0
        self._anchor, self._k, self._last_grid = None, 0, -np.inf
        if self._segment_samples:
            self._segment_samples = 0
            self._restart()

    def _accept_jumped(self) -> int:
        accepted = 0
        for stream, s in self._streams.items():
            parts, s.jumped = s.jumped, []
            if parts:
                t, x = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
                accepted += self._accept(stream, t, x, np.maximum.accumulate(np.concatenate([[-np.inf], t]))[:-1])
        return accepted

    def _accept(self, stream: str, t: np.ndarray, x: np.ndarray, newest: np.ndarray) -> int:
        accept = t > newest
        self.stats.duplicate += int(np.count_nonzero(t == newest))
        self.stats.late += int(np.count_nonzero(t < newest))
        return self._append(stream, t[accept], x[accept])

    def _append(self, stream: str, t: np.ndarray, x: np.ndarray) -> int:
        """Hold accepted samples (increasing stamps, all newer than the stream's newest) for the grid."""
        s = self._streams[stream]
        if t.size == 0:
            return 0
        self.stats.accepted[stream] += t.size
        self.stats.first_stamp.setdefault(stream, float(t[0]))
        self.stats.last_stamp[stream] = float(t[-1])
        self.stats.overflow += s.append(t, x, cap=self.pending_cap)
        return int(t.size)

    def _infer_rate(self) -> None:
        """The grid rate from the excitation's first INFER_SAMPLES stamps, or from the response's
        when the excitation is held (its steps longer than HOLD_PERIODS of the response's)."""
        ex, re = self._streams["excitation"], self._streams["response"]
        if re.size >= INFER_SAMPLES and ex.size >= 2 and ex.median_step() > HOLD_PERIODS * re.median_step():
            self.rate = 1.0 / re.median_step()
        elif ex.size >= INFER_SAMPLES:
            self.rate = 1.0 / ex.median_step()
        else:
            return
        self.stats.sample_rate = self.rate

    def _decide_hold(self) -> bool | None:
        """Whether the excitation is held: decided once, from its first stamps (two at least)."""
        ex = self._streams["excitation"]
        if self.held is None and ex.size >= 2:
            self.held = self.stats.excitation_held = ex.median_step() > HOLD_PERIODS / self.rate
        return self.held

    def _response_interpolation(self) -> str:
        """How the response is read at the grid points: linearly when it is slower than the grid
        (its median step over SPARSE_RESPONSE grid periods, e.g. a 25 Hz sensor on a 50 Hz grid: a
        held sensor sample would put a staircase into the dynamics), else ``interpolation``."""
        re = self._streams["response"]
        if self.sparse_response is None and re.size >= 2:
            self.sparse_response = re.median_step() > SPARSE_RESPONSE / self.rate
        return "linear" if self.sparse_response else self.config.interpolation

    def _next_grid_time(self, clock: _Stream, start: float, tol: float) -> float | None:
        """The first grid point not yet emitted and not before ``start`` (None: wait for data)."""
        if self.config.sample_rate:  # fixed grid t_a + k / fs
            if self._anchor is None:
                self._anchor, self._k = float(clock.t[0]), 0
            self._k = max(self._k, math.ceil((start - tol - self._anchor) * self.rate))
            return self._anchor + self._k / self.rate
        later = clock.t[(clock.t > self._last_grid) & (clock.t >= start - tol)]  # clocked by the stream's stamps
        return float(later[0]) if later.size else None

    def _grid_until(self, clock: _Stream, first: float, end: float) -> np.ndarray:
        if self.config.sample_rate:
            last_k = math.floor((end - self._anchor) * self.rate)
            return self._anchor + np.arange(self._k, last_k + 1) / self.rate
        return clock.t[(clock.t >= first) & (clock.t <= end)]

    def _emit(self) -> None:
        if self.rate is None:
            self._infer_rate()
            if self.rate is None:
                return
        cfg = self.config
        tol = GRID_TOLERANCE / self.rate
        max_gap = cfg.max_gap or 5.0 / self.rate
        ex, re = self._streams["excitation"], self._streams["response"]
        while ex.size and re.size:
            held = self._decide_hold()
            clock = re if held else ex
            hold = cfg.max_gap or math.inf  # how long a held excitation sample lasts without a next one
            tk = self._next_grid_time(clock, max(ex.t[0], re.t[0]), tol)
            if tk is None:
                return
            ends, starts = {}, []
            for name, s in (("excitation", ex), ("response", re)):
                starts.append(int(np.searchsorted(s.t, tk + tol, side="right")) - 1)
                ends[name] = (s.segment_end(max(starts[-1], 0), hold, hold) if held and s is ex
                              else s.segment_end(max(starts[-1], 0), max_gap))
            end = min(e for e, _ in ends.values())
            grid = self._grid_until(clock, tk, end + tol)  # from tk on
            if grid.size:
                self._emit_grid(grid, ex.values_at(grid, tol, "zoh" if held else cfg.interpolation, starts[0]),
                                re.values_at(grid, tol, self._response_interpolation(), starts[1]))
                for s in (ex, re):  # keep the last sample at or before the newest grid point
                    s.drop(max(0, int(np.searchsorted(s.t, grid[-1] + tol, side="right")) - 1))
            blocked = [(name, resume) for name, (e, resume) in ends.items() if resume is not None and e <= end]
            if not blocked:
                return
            name, resume = blocked[0]
            s = self._streams[name]
            s.drop(int(np.searchsorted(s.t, resume, side="left")))
            if s is clock:
                self._anchor = None
            if self._segment_samples:
                self.stats.gaps += 1
                self._segment_samples = 0
                self._restart()

    def _emit_grid(self, grid: np.ndarray, v: np.ndarray, y: np.ndarray) -> None:
        self._last_grid = float(grid[-1])
        if self.config.sample_rate:
            self._k = round((self._last_grid - self._anchor) * self.rate) + 1
        self._segment_samples += grid.size
        self.stats.aligned += grid.size
        self._sink(grid, v, y)
