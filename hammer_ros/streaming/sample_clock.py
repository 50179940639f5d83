"""Sample stamps for messages that carry no stamp (std_msgs/Float64, Float64MultiArray, ...).

The receive time of such a message is its only clue, and on a loaded machine it jitters by more
than a sample period (messages arrive late and in bursts), so putting each sample at its receive
time would repeat and skip samples on the grid and tear the excitation apart from the response.
Instead the samples of each stream are *counted*:

    stamp(i) = base + i / fs,   base = min over the last ``horizon`` seconds of (r_m - i_m / fs),

where r_m is the receive time of message m and i_m the index of its last sample (the batch
convention: the last sample of a message is the newest one). ``base`` is set by the least
delayed message, so jitter and bursts never move a sample. Stamps lie on one grid shared by all
streams, anchored at the first stamp issued, by the *reference* stream (the first one stamped).
A stream's place on the grid is a whole number of periods: for the reference, its base from the
anchor; for another stream, its base from the reference's base. Both are rounded with
hysteresis (a place changes only when the base moves more than ``HYSTERESIS`` periods past the
half-way point), so an excitation and a response published together, whose bases differ by a
small fraction of a period, always land on the same grid point: rounding each base on its own
would split them for as long as the bases straddle a half period, a one-sample misalignment
that the identification cannot tell from the plant. A move of the reference's base moves every
stream with it.

A stall of the subscriber (messages queued, then delivered in a burst) moves nothing. A receive
time more than ``resync`` seconds before the count predicts (the publisher runs faster than fs)
restarts the count of that stream (``restarts``). A receive time more than ``resync`` after it is
a stall or a publisher pause (or samples lost upstream), and the message itself cannot tell which:
it is stamped on the count, and the messages after it decide. If they arrive faster than ``BURST``
x fs, a stall's queue is being delivered: the count goes on, and the bases from before the stall
stay until the burst has caught up and ended (a restart at the stall's first message set the base
from that late message; the burst's messages, each a period less delayed than the last, then
moved the stream's place back a period per message: repeated stamps, and the response a sample
off the excitation for as long as the burst lasted). If they arrive at about fs, the publisher
paused: the count restarts at the first late message (at the message that decides, when that one
came another ``resync`` after the first: the publisher paused twice). A pause shorter than ``resync`` is removed
from the stream (the samples stay contiguous, which is exact when the plant paused too) until the
``horizon`` forgets the pre-pause messages; then the stamps jump forward and the engine sees a gap.

With fs unknown (0), the rate is inferred from the first ``infer_seconds`` of the first stream:
the least-squares slope of the sample count over the receive time, rounded to 3 significant
digits; the samples seen meanwhile are not stamped (``stamps`` returns None).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

INFER_SECONDS = 2.0
HYSTERESIS = 0.25  # periods past the half-way point before a stream's place on the grid moves
INFER_MIN_MESSAGES = 16
BURST = 1.5  # arrivals faster than this many times fs after a late message: a stall's burst


def _round_significant(x: float, digits: int = 3) -> float:
    return round(x, digits - 1 - int(math.floor(math.log10(abs(x)))))


def _round_with_hysteresis(x: float, current: int | None) -> int:
    """``round(x)``, except that ``current`` stays while ``x`` is within 0.5 + HYSTERESIS of it."""
    if current is not None and abs(x - current) <= 0.5 + HYSTERESIS:
        return current
    return round(x)


class _CountedStream:
    def __init__(self) -> None:
        self.count = 0  # samples stamped since the last (re)start
        self.history: deque[tuple[float, float]] = deque()  # (receive time, base candidate), candidates increasing
        self.place: int | None = None  # periods from the anchor (reference) or from the reference's base
        # the first late message while a stall and a pause are told apart: (receive time, count before it, its samples)
        self.late_since: tuple[float, int, int] | None = None

    def restart(self) -> None:
        self.count = 0
        self.history.clear()
        self.place = None
        self.late_since = None

    def paused(self, receive_time: float, count: int, period: float) -> bool:
        """Whether the messages since the first late one say that the publisher paused: their
        samples arrived no faster than ``BURST`` x fs (a stall's queue arrives faster)."""
        since, before, samples = self.late_since
        return (self.count + count - before - samples) * period <= BURST * (receive_time - since)

    def restart_after_pause(self, receive_time: float, count: int, period: float, resync: float) -> float:
        """Restart the count after a publisher pause: at the first late message (the publisher's
        first after the pause) when this message continues it, else here (the publisher paused
        again after it). Returns this message's base candidate."""
        since, before, samples = self.late_since
        first = since - (samples - 1) * period
        candidate = receive_time - (self.count - before + count - 1) * period
        if candidate - first > resync:
            self.restart()
            return receive_time - (count - 1) * period
        self.count -= before
        self.history = deque([(since, first)])
        self.place = None
        self.late_since = None
        return candidate


class ArrivalStamper:
    """Stamps on one grid of rate ``rate`` (Hz, 0 = infer) for unstamped streams, by name."""

    def __init__(self, rate: float = 0.0, horizon: float = 2.0, resync: float = 0.5) -> None:
        self.rate = float(rate)
        self.horizon = horizon
        self.resync = resync
        self.restarts = 0
        self._streams: dict[str, _CountedStream] = {}
        self._anchor: float | None = None
        self._reference: _CountedStream | None = None  # the first stream stamped: it places the others
        self._inference: list[tuple[float, int]] = []  # (receive time, cumulative samples) of one stream
        self._inference_stream: str | None = None

    def set_rate(self, rate: float) -> None:
        """A new grid rate (0 = infer again): every stream restarts its count."""
        self.__init__(rate, self.horizon, self.resync)

    def stamps(self, stream: str, receive_time: float, count: int) -> np.ndarray | None:
        """Stamps of the ``count`` samples of one message of ``stream`` received at
        ``receive_time`` (s), oldest first; None while the rate is still being inferred."""
        first = self.first_stamp(stream, receive_time, count)
        return None if first is None else first + np.arange(count) / self.rate

    def first_stamp(self, stream: str, receive_time: float, count: int) -> float | None:
        """The stamp of the first of the ``count`` samples of one message (the others follow at
        1/rate); None while the rate is still being inferred. Pure float arithmetic: this runs
        once per received message."""
        if self.rate <= 0 and not self._infer(stream, receive_time, count):
            return None
        s = self._streams.get(stream)
        if s is None:
            s = self._streams[stream] = _CountedStream()
        period = 1.0 / self.rate
        candidate = receive_time - (s.count + count - 1) * period
        history = s.history
        if history:
            late = candidate - history[0][1]
            if late < -self.resync:  # the publisher runs faster than fs
                self.restarts += 1
                s.restart()
                candidate = receive_time - (count - 1) * period
            elif late > self.resync:
                if s.late_since is None:  # alone it cannot tell a stall from a pause: stamped on the count
                    s.late_since = (receive_time, s.count, count)
                elif s.paused(receive_time, count, period):
                    self.restarts += 1
                    candidate = s.restart_after_pause(receive_time, count, period, self.resync)
                    history = s.history
            elif s.late_since is not None and count * period <= BURST * (receive_time - history[-1][0]):
                s.late_since = None  # a stall: its burst has caught up and ended (history[-1]: the last message)
        while history and history[-1][1] >= candidate:
            history.pop()
        history.append((receive_time, candidate))
        while s.late_since is None and history[0][0] < receive_time - self.horizon:
            history.popleft()  # (a late message keeps the bases from before it until it is understood)
        base = history[0][1]
        if self._reference is None:
            self._reference, self._anchor = s, base  # its first stamp: count 0
        reference = self._reference
        reference_base = reference.history[0][1]
        if s is reference:
            s.place = _round_with_hysteresis((base - self._anchor) * self.rate, s.place)
            place = s.place
        else:
            s.place = _round_with_hysteresis((base - reference_base) * self.rate, s.place)
            place = s.place + reference.place  # set: the reference was stamped first
        first = self._anchor + (place + s.count) * period
        s.count += count
        return first

    def first_stamps(self, stream: str, receive_times: np.ndarray, count: int) -> np.ndarray:
        """``first_stamp`` of consecutive messages of ``stream``, each of ``count`` samples,
        received at ``receive_times`` (NaN where it gives None): the same floats, computed for
        a whole flush at once. While nothing restarts the count or moves the stream's place,
        the base of message m is the sliding minimum of the candidates over the horizon,

            base_m = min(min{c_h : r_h >= r_m - horizon, h in the history}, min_{j <= m} c_j),

        (the history's deque is that minimum's monotone queue); the first message that restarts,
        moves the place, arrives out of order or lies a horizon after the flush's first one is
        stamped by ``first_stamp``, and the rest of the flush resumes at once after it."""
        r = np.asarray(receive_times, dtype=float)
        firsts = np.empty(r.size)
        i = 0
        while i < r.size:
            done = self._first_stamps_at_once(stream, r[i:], count, firsts[i:]) if self.rate > 0 else 0
            if done == 0:
                first = self.first_stamp(stream, float(r[i]), count)
                firsts[i] = math.nan if first is None else first
                done = 1
            i += done
        return firsts

    def _first_stamps_at_once(self, stream: str, r: np.ndarray, count: int, out: np.ndarray) -> int:
        """Stamp the longest prefix of ``r`` that ``first_stamps``' formula covers into ``out``
        and update the state as ``first_stamp`` would; returns its length (0: none)."""
        s = self._streams.get(stream)
        reference = self._reference
        if (s is None or not s.history or s.place is None or s.late_since is not None
                or reference is None or reference.place is None):
            return 0
        period = 1.0 / self.rate
        m = np.arange(r.size)
        candidates = r - (s.count + count * m + count - 1) * period
        history_r = np.array([h[0] for h in s.history])
        history_c = np.array([h[1] for h in s.history])
        if history_r.size > 1 and np.any(np.diff(history_r) < 0):  # a receive clock that went back
            return 0
        oldest = np.searchsorted(history_r, r - self.horizon, side="left")  # first history entry still inside
        inside = np.append(history_c, math.inf)[oldest]
        bases = np.minimum(inside, np.minimum.accumulate(candidates))
        previous = np.concatenate([[history_c[0]], bases[:-1]])
        if s is reference:
            x = (bases - self._anchor) * self.rate
        else:
            x = (bases - reference.history[0][1]) * self.rate
        valid = ((np.diff(r, prepend=history_r[-1]) >= 0) & (np.abs(candidates - previous) <= self.resync)
                 & (r - self.horizon <= r[0]) & (np.abs(x - s.place) <= 0.5 + HYSTERESIS))
        done = int(np.argmin(valid)) if not valid.all() else r.size
        if done == 0:
            return 0
        place = s.place if s is reference else s.place + reference.place
        out[:done] = self._anchor + (place + s.count + count * m[:done]) * period
        # the history's new deque: the entries still inside the horizon that no later candidate undercuts
        keep_r = np.concatenate([history_r[oldest[done - 1]:], r[:done]])
        keep_c = np.concatenate([history_c[oldest[done - 1]:], candidates[:done]])
        later = np.minimum.accumulate(keep_c[::-1])[::-1]
        kept = keep_c < np.append(later[1:], math.inf)
        s.history = deque(zip(keep_r[kept].tolist(), keep_c[kept].tolist()))
        s.count += count * done
        return done

    def _infer(self, stream: str, receive_time: float, count: int) -> bool:
        if self._inference_stream is None:
            self._inference_stream = stream
        if stream != self._inference_stream:
            return False
        total = (self._inference[-1][1] if self._inference else 0) + count
        self._inference.append((receive_time, total))
        t = np.array([r for r, _ in self._inference])
        if t.size < INFER_MIN_MESSAGES or t[-1] - t[0] < INFER_SECONDS:
            return False
        n = np.array([c for _, c in self._inference], dtype=float)
        slope = float(np.polyfit(t - t[0], n, 1)[0])
        self._inference.clear()
        if not (math.isfinite(slope) and slope > 0):
            self._inference_stream = None
            return False
        self.rate = _round_significant(slope)
        return False  # this message only completes the inference; stamping starts with the next one
