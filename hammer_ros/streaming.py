"""The streaming identification engine (pure numpy; the ROS node and ``replay`` are thin adapters).

Pipeline, per batch of timestamped samples of either stream:

1. **Screening.** Non-finite values or stamps, and values above MAX_ABS_SAMPLE, are skipped
   (``nan_skipped``). A stamp equal to the newest accepted stamp of its stream is a
   ``duplicate``, an older one is ``late``; both are skipped (the grid only moves forward). When
   both streams jump back by more than max(1 s, max_gap) (sim time reset, bag loop) the
   alignment restarts on the new timeline (``clock_resets``). Samples waiting for the other
   stream are bounded (``pending_cap``; the oldest are dropped: ``overflow``).
2. **Alignment** on one grid. With ``sample_rate`` fs > 0 the grid is t_k = t_a + k / fs,
   anchored at the first excitation stamp t_a (re-anchored after an excitation gap), so a
   uniformly sampled command lands on it exactly. With ``sample_rate`` 0 the excitation stamps
   themselves are the grid (the command clocks the identification; no drift against a
   slightly-off nominal rate) and fs, estimated from the median spacing of the first 16
   excitation stamps, only sets the tolerances. A grid point is emitted once BOTH streams have
   a sample at or after it; its values are the zero-order hold (last sample with stamp
   <= t_k + tol) or the linear interpolation of each stream, tol = 0.01 / fs.
3. **Gap policy.** Consecutive stamps of one stream further apart than ``max_gap`` (default
   5 / fs) are a gap: the grid points inside the gap are not emitted and the window restarts
   empty after it (``gaps`` counts the restarts). Samples on both sides of a gap are never
   mixed in one lag product or regression row; the last model stays valid until the new window
   is ``min_fill`` full again.
4. **Correlation sums** over the window of the last W aligned samples (paper 000 eq. 8 and
   Remark 2): with L = min(W, samples) and T = tau_max, the centres k = T .. L-1-T give
   N + 1 = L - 2T products per lag,

       phi_vv(tau)  = 1/(N+1) sum_k v(k) v(k-tau)
       phi_yv(tau)  = 1/(N+1) sum_k y(k) v(k-tau)
       phi_yvv(tau) = 1/(N+1) sum_k y(k) v(k-tau)^2      (second order, paper 003 eq. 21)

   for tau = -T..T: exactly ``correlation.cross_correlation`` on the window. A new sample
   completes the centre k = newest - T, whose O(T) products are formed once (vectorised per
   chunk: one C correlation loop per row, or real FFTs from T = FFT_MIN_TAU_MAX) into a block
   of consecutive centres; a block leaves the sums whole once the window has passed it, and
   the part of the oldest block already outside is subtracted when the correlations are read.
   Every W samples the sums are re-added from the blocks, so rounding cannot drift.
   With ``forgetting`` lambda < 1 the sums are instead exponentially weighted over every centre
   since the window (re)started: weight lambda^(c - k) for centre k when the newest centre is c,
   divided by the total weight (``correlation.weighted_cross_correlation`` is the batch form).
5. **Solve** on an immutable snapshot (``solve_snapshot``, safe in a worker thread): CLS ARX /
   mu-Markov step 1 on the correlation sums, step 2 on the raw window; any other method through
   ``methods.identify`` on the raw window. No model (``status``) while the window fills, when
   the input is not persistently exciting (absolutely, or relative to the windows behind the
   published models: ``min_excitation``), when the published model fits the window clearly
   better (``kept``), or when the method fails or raises (never propagated).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np
import scipy.fft

from .errors import HammerRosError, UsageError
from .methods import METHODS, IdentifyOptions, identify
from .result import IdentificationResult, fit_percent

INFER_SAMPLES = 16  # excitation stamps used to infer the sample rate
GRID_TOLERANCE = 0.01  # of a sample period: stamps this close to a grid point are on it
PE_CONDITION_LIMIT = 1e8  # cond(R) above this: input not persistently exciting
KEEP_MARGIN = 5.0  # fit points by which the published model must beat a new estimate on its window to stay
CHUNK = 4096  # aligned samples per vectorised update (bounds the buffer headroom)
BLOCK_CENTRES = 256  # sliding window: fewest centres per block of lag-product sums ...
BLOCKS_PER_WINDOW = 64  # ... and at most about this many blocks per window (their memory)
CLS_STRUCTURES = {"cls-arx": "arx", "cls-markov": "markov"}
# Documented resource limits (README "Robustness"): memory ~ 16 bytes x (window + 4 window pending
# per stream) and one solve's regression; work per sample ~ tau_max.
MAX_WINDOW = 1_000_000
MAX_TAU_MAX = 2_000
MAX_ABS_SAMPLE = 1e100  # |x| above this is screened like NaN: cubes of window sums stay finite
PENDING_SAMPLES = 2_000_000  # per stream, waiting for the other stream (32 MB); at least 4 windows
CLOCK_RESET_SECONDS = 1.0  # a stamp this much (or max_gap, if longer) older than its stream's newest: clock reset
STREAMS = ("excitation", "response")


@dataclass(frozen=True)
class EngineConfig:
    """Configuration of the engine; field names are the node's parameter names."""

    sample_rate: float = 0.0  # Hz of the common grid; 0 = infer from the excitation stamps
    window: int = 4000  # W: samples in the sliding window (also the raw window kept)
    forgetting: float = 1.0  # 1.0 = exact sliding window; < 1 = exponential forgetting
    tau_max: int = 60
    method: str = "cls-markov"  # any methods.METHODS name except semiparametric
    order: int = 3
    delay: int = 1
    mu: int | None = None
    poly: int = 3
    partition: tuple[float, ...] | None = None
    interpolation: str = "zoh"  # or "linear"
    max_gap: float = 0.0  # seconds; 0 = 5 / sample_rate
    min_fill: float = 0.25  # fraction of the window needed before the first solve
    min_excitation: float = 0.1  # input std needed, relative to the windows behind the published models; 0 = off

    def validated(self) -> EngineConfig:
        """self, or a UsageError naming the first invalid field and why."""
        def bad(name: str, why: str) -> UsageError:
            return UsageError(f"{name}: {why} (got {getattr(self, name)!r})")

        for f in fields(self):  # types first: a YAML string or list must not reach the comparisons
            value, kind = getattr(self, f.name), _FIELD_KINDS[f.name]
            if value is None and f.name in ("mu", "partition"):
                continue
            if kind is int and (isinstance(value, bool) or not isinstance(value, (int, np.integer))):
                raise bad(f.name, "must be an integer")
            if kind is float and (isinstance(value, bool) or not isinstance(value, (int, float, np.number))):
                raise bad(f.name, "must be a number")
            if kind is str and not isinstance(value, str):
                raise bad(f.name, "must be a string")
            if kind is tuple and not (isinstance(value, tuple)
                                      and all(isinstance(c, (int, float)) and math.isfinite(c) for c in value)):
                raise bad(f.name, "must be a list of numbers")
        if not (math.isfinite(self.sample_rate) and self.sample_rate >= 0):
            raise bad("sample_rate", "must be >= 0 Hz (0 = infer)")
        if not 1 <= self.tau_max <= MAX_TAU_MAX:
            raise bad("tau_max", f"must be in 1..{MAX_TAU_MAX}")
        if self.window < max(16, 2 * self.tau_max + 2):
            raise bad("window", f"must be >= max(16, 2 tau_max + 2) = {max(16, 2 * self.tau_max + 2)} samples")
        if self.window > MAX_WINDOW:
            raise bad("window", f"must be <= {MAX_WINDOW} samples (the raw window is kept in memory)")
        if not 0.0 < self.forgetting <= 1.0:
            raise bad("forgetting", "must be in (0, 1]")
        if self.method not in METHODS:
            raise bad("method", f"unknown method (choose from {', '.join(METHODS)})")
        if self.method == "semiparametric":
            raise bad("method", "semiparametric needs a separate single-harmonic record; not available streaming")
        if self.order < 1:
            raise bad("order", "must be >= 1")
        if not 0 <= self.delay <= self.order:
            raise bad("delay", f"must be in 0..order ({self.order})")
        if self.mu is not None and self.mu < 1:
            raise bad("mu", "must be >= 1")
        if self.poly < 1:
            raise bad("poly", "must be >= 1")
        if self.partition is not None and (len(self.partition) == 0 or np.any(np.diff(self.partition) <= 0)):
            raise bad("partition", "breakpoints must be strictly increasing")
        if self.interpolation not in ("zoh", "linear"):
            raise bad("interpolation", "must be 'zoh' or 'linear'")
        if not (math.isfinite(self.max_gap) and self.max_gap >= 0):
            raise bad("max_gap", "must be >= 0 s (0 = 5 sample periods)")
        if not 0.0 < self.min_fill <= 1.0:
            raise bad("min_fill", "must be in (0, 1]")
        if not 0.0 <= self.min_excitation <= 1.0:
            raise bad("min_excitation", "must be in [0, 1] (0 = off)")
        return self

    def identify_options(self) -> IdentifyOptions:
        return IdentifyOptions(order=self.order, delay=self.delay, mu=self.mu, poly=self.poly,
                               partition=self.partition, tau_max=self.tau_max)


_FIELD_KINDS = {"sample_rate": float, "window": int, "forgetting": float, "tau_max": int, "method": str, "order": int,
                "delay": int, "mu": int, "poly": int, "partition": tuple, "interpolation": str, "max_gap": float,
                "min_fill": float, "min_excitation": float}


@dataclass
class EngineStats:
    """Counters of the engine (monotonic except ``window_fill``/``window_samples``)."""

    received_excitation: int = 0
    received_response: int = 0
    aligned: int = 0
    nan_skipped: int = 0
    late: int = 0
    duplicate: int = 0
    unstamped: int = 0  # batch messages that could not be placed (rate still unknown)
    overflow: int = 0  # pending samples dropped because the other stream stalled
    gaps: int = 0
    clock_resets: int = 0  # both streams' stamps jumped back (sim time reset, bag loop): alignment restarted
    aligned_before_reset: int = 0  # ``aligned`` at the last clock reset (the rates count from there)
    window_samples: int = 0
    window_fill: float = 0.0
    sample_rate: float = 0.0  # grid rate in use (configured or inferred), 0 = not yet known
    solves: int = 0
    solve_errors: int = 0  # solves that gave no model, for any reason below or the window filling
    not_exciting: int = 0  # ... because the input was not persistently exciting
    kept_published: int = 0  # ... because the published model fits the window clearly better
    solve_failures: int = 0  # ... because the method failed on the data (e.g. an empty PLLS interval)
    solve_exceptions: int = 0  # ... because of an unexpected exception (logged; ingestion goes on)
    first_stamp: dict = field(default_factory=dict)  # stream -> first accepted stamp
    last_stamp: dict = field(default_factory=dict)  # stream -> newest accepted stamp
    accepted: dict = field(default_factory=lambda: {s: 0 for s in STREAMS})
    bad_values: dict = field(default_factory=lambda: {s: 0 for s in STREAMS})  # finite stamp, non-finite value

    def missing(self, stream: str) -> int:
        """Samples of ``stream`` that the stamps say were sent but never arrived (a uniform
        stream at ``sample_rate`` since its first stamp, or the last clock reset; 0 while the
        rate is unknown): what the middleware dropped before the node saw it."""
        span = self.last_stamp.get(stream, 0.0) - self.first_stamp.get(stream, 0.0)
        if not self.sample_rate or stream not in self.first_stamp:
            return 0
        return max(0, round(span * self.sample_rate) + 1 - self.accepted[stream] - self.bad_values[stream])

    def rate(self, stream: str) -> float:
        """Accepted samples per second of stamp time for ``stream`` ("excitation", "response")."""
        span = self.last_stamp.get(stream, 0.0) - self.first_stamp.get(stream, 0.0)
        return (self.accepted[stream] - 1) / span if span > 0 else 0.0

    @property
    def aligned_rate(self) -> float:
        """Grid samples per second of stamp time since the first excitation sample."""
        span = self.last_stamp.get("excitation", 0.0) - self.first_stamp.get("excitation", 0.0)
        return (self.aligned - self.aligned_before_reset) / span if span > 0 else 0.0

    def as_dict(self) -> dict:
        internal = ("first_stamp", "last_stamp", "accepted", "bad_values")
        doc = {k: v for k, v in asdict(self).items() if k not in internal}
        doc.update(received_rate_excitation=self.rate("excitation"), received_rate_response=self.rate("response"),
                   aligned_rate=self.aligned_rate)
        return doc

    def copy(self) -> EngineStats:
        return replace(self, first_stamp=dict(self.first_stamp), last_stamp=dict(self.last_stamp),
                       accepted=dict(self.accepted), bad_values=dict(self.bad_values))


@dataclass(frozen=True, eq=False)
class EngineSnapshot:
    """Everything a solve needs, copied out of the engine (immutable by convention)."""

    config: EngineConfig
    phi_vv: np.ndarray  # normalised correlations, index tau + tau_max
    phi_yv: np.ndarray
    phi_yvv: np.ndarray
    weight: float  # number of products N + 1 (sliding window) or total weight (forgetting)
    v: np.ndarray  # raw window (aligned samples, oldest first)
    y: np.ndarray
    stamp: float  # grid time of the newest sample (nan before the first)
    stats: EngineStats
    published: IdentificationResult | None = None  # the model published last (see ``solve_snapshot``)
    reference_std: float = 0.0  # largest input std of the windows behind the published models


@dataclass(frozen=True, eq=False)
class SolveOutcome:
    """The result of one solve; ``reason`` says why when not ``ok``."""

    ok: bool
    reason: str
    result: IdentificationResult | None
    doc: dict | None  # the identify --json document (contract keys)
    condition_number: float  # of the input autocorrelation matrix (persistent excitation)
    solve_seconds: float
    samples: int
    stamp: float
    status: str = "ok"  # ok | filling | not_exciting | kept | failed (the method rejected the data) | exception
    input_std: float = float("nan")  # of the window's input


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

    def segment_end(self, index: int, max_gap: float) -> tuple[float, float | None]:
        """(stamp where the segment holding sample ``index`` ends, stamp of the first sample after
        the gap that ends it, or None while the segment is still open)."""
        jumps = np.flatnonzero(np.diff(self.t[index:]) > max_gap)
        if jumps.size == 0:
            return float(self.t[-1]), None
        j = index + int(jumps[0])
        return float(self.t[j]), float(self.t[j + 1])

    def values_at(self, grid: np.ndarray, tol: float, interpolation: str) -> np.ndarray:
        if interpolation == "linear":
            return np.interp(grid, self.t, self.x)
        t, x = self.t, self.x
        start = int(np.searchsorted(t, grid[0] + tol, side="right")) - 1
        stamps = t[max(start, 0) : start + grid.size]
        if start >= 0 and stamps.size == grid.size and np.all(np.abs(stamps - grid) <= tol):
            return x[start : start + grid.size]  # a sample at every grid point: the hold is the samples
        return x[np.searchsorted(t, grid + tol, side="right") - 1]


FFT_MIN_TAU_MAX = 128  # from here on the lag products of a block are summed by FFT (faster than
                       # the direct O(rows x tau_max) loops for blocks of >= 1000 rows; same sums
                       # to ~2e-16 relative)


def _lag_products(v: np.ndarray, y: np.ndarray, tau_max: int, weights: np.ndarray | None = None) -> np.ndarray:
    """Sums over the centres k = T..len-1-T of [v(k), y(k), y(k)] times [v, v, v^2](k - tau),
    tau = -T..T, as a (3, 2T+1) array (optionally weighted per centre).

    ``np.correlate(x, c, 'valid')[j] = sum_n x(n + j) c(n)``: with x = v from the first sample
    and c the centres, j = T - tau; one C loop per row, no lag matrix in memory. For
    T >= FFT_MIN_TAU_MAX the same sums come from real FFTs of length >= len(v) (c is shorter
    than x, so the circular correlation does not wrap for j <= 2T)."""
    rows = v.size - 2 * tau_max
    centre_v, centre_y = v[tau_max : tau_max + rows], y[tau_max : tau_max + rows]
    if weights is not None:
        centre_v, centre_y = centre_v * weights[:rows], centre_y * weights[:rows]
    if tau_max >= FFT_MIN_TAU_MAX:
        n = scipy.fft.next_fast_len(v.size, real=True)
        x = scipy.fft.rfft(np.stack([v, v * v]), n, axis=1)
        c = np.conj(scipy.fft.rfft(np.stack([centre_v, centre_y]), n, axis=1))
        sums = scipy.fft.irfft(np.stack([x[0] * c[0], x[0] * c[1], x[1] * c[1]]), n, axis=1)[:, : 2 * tau_max + 1]
    else:
        sums = np.stack([np.correlate(v, centre_v, "valid"), np.correlate(v, centre_y, "valid"),
                         np.correlate(v * v, centre_y, "valid")])
    return sums[:, ::-1]


class _Block:
    """Lag-product sums of the consecutive centres lo..hi (a sliding window's unit of removal)."""

    __slots__ = ("hi", "lo", "sums")

    def __init__(self, lo: int, hi: int, sums: np.ndarray) -> None:
        self.lo, self.hi, self.sums = lo, hi, sums


class _CorrelationWindow:
    """Raw window of aligned samples and the recursive correlation sums over it.

    Sliding window (forgetting 1): the products of every centre are formed once, when it
    arrives, and summed into blocks of >= ``block`` consecutive centres; ``sums`` is the total
    of the blocks. A block leaves whole (its sums subtracted) once the window has passed it;
    the part of the oldest block already outside is subtracted only when the correlations are
    read (once per solve), and ``sums`` is re-added from the blocks every W samples, so
    rounding cannot drift. Forgetting: ``sums`` decays and the new products are added."""

    def __init__(self, window: int, tau_max: int, forgetting: float) -> None:
        self.window, self.tau_max, self.forgetting = window, tau_max, forgetting
        self.block = max(BLOCK_CENTRES, window // BLOCKS_PER_WINDOW)
        self.capacity = window + self.block + 2 * (CHUNK + tau_max)  # the oldest block's samples too
        self.v = np.empty(self.capacity)
        self.y = np.empty(self.capacity)
        self.reset()

    def reset(self) -> None:
        self.count = 0  # samples since the (re)start of the segment
        self.stored = 0  # samples held in self.v[:stored] (the newest ones)
        self.window_start = 0  # segment index of the window's oldest sample
        self.sums = np.zeros((3, 2 * self.tau_max + 1))
        self.weight = 0.0
        self.centres = (0, -1)  # [lo, hi] segment indices of the window's centres
        self.blocks: deque[_Block] = deque()  # sliding: consecutive centre blocks, oldest first
        self.since_resync = 0

    def _local(self, start: int, stop: int) -> slice:
        """Slice of the stored arrays holding segment indices start..stop-1."""
        offset = self.count - self.stored
        return slice(start - offset, stop - offset)

    def _products(self, lo: int, hi: int, weights: np.ndarray | None = None) -> np.ndarray:
        if hi < lo:
            return np.zeros_like(self.sums)
        s = self._local(lo - self.tau_max, hi + self.tau_max + 1)
        return _lag_products(self.v[s], self.y[s], self.tau_max, weights)

    def _target_centres(self) -> tuple[int, int]:
        return self.window_start + self.tau_max, self.count - 1 - self.tau_max

    def add(self, v: np.ndarray, y: np.ndarray) -> None:
        for start in range(0, v.size, CHUNK):
            self._add_chunk(v[start : start + CHUNK], y[start : start + CHUNK])

    def _add_chunk(self, v: np.ndarray, y: np.ndarray) -> None:
        m = v.size
        if self.stored + m > self.capacity:
            oldest = min(self.window_start, self.blocks[0].lo - self.tau_max) if self.blocks else self.window_start
            keep = min(self.stored, self.count - oldest)
            self.v[:keep] = self.v[self.stored - keep : self.stored]
            self.y[:keep] = self.y[self.stored - keep : self.stored]
            self.stored = keep
        self.v[self.stored : self.stored + m] = v
        self.y[self.stored : self.stored + m] = y
        self.stored += m
        self.count += m
        self.window_start = max(self.window_start, self.count - self.window)
        if self.forgetting < 1.0:
            self._update_forgetting()
        else:
            self._update_sliding(m)

    def _update_sliding(self, m: int) -> None:
        new_lo, new_hi = self._target_centres()
        first = self.blocks[-1].hi + 1 if self.blocks else new_lo
        if first < new_lo:  # a chunk longer than the window: everything summed so far has left it
            self.blocks.clear()
            self.sums = np.zeros_like(self.sums)
            first = new_lo
        if new_hi >= first:
            products = self._products(first, new_hi)
            self.sums += products
            last = self.blocks[-1] if self.blocks else None
            if last is not None and last.hi - last.lo + 1 < self.block:
                last.sums += products
                last.hi = new_hi
            else:
                self.blocks.append(_Block(first, new_hi, products))
        while self.blocks and self.blocks[0].hi < new_lo:
            self.sums -= self.blocks.popleft().sums
        self.since_resync += m
        if self.since_resync >= self.window:
            self.sums = np.sum([b.sums for b in self.blocks], axis=0) if self.blocks else np.zeros_like(self.sums)
            self.since_resync = 0
        self.centres = (new_lo, new_hi)
        self.weight = float(max(0, new_hi - new_lo + 1))

    def window_sums(self) -> np.ndarray:
        """The sums over the window's centres (sliding: without the oldest block's part outside)."""
        if self.forgetting < 1.0 or not self.blocks or self.blocks[0].lo >= self.centres[0]:
            return self.sums
        return self.sums - self._products(self.blocks[0].lo, self.centres[0] - 1)

    def _update_forgetting(self) -> None:
        """Every centre since the (re)start is weighted in, also when a chunk exceeds the window."""
        lo, hi = self.centres
        new_hi = self.count - 1 - self.tau_max
        first = hi + 1 if hi >= lo else self.tau_max
        if new_hi < first:
            return
        decay = self.forgetting ** np.arange(new_hi - first, -1, -1)
        shrink = self.forgetting ** (new_hi - hi) if hi >= lo else 0.0
        self.sums = shrink * self.sums + self._products(first, new_hi, decay)
        self.weight = shrink * self.weight + float(decay.sum())
        self.centres = (lo if hi >= lo else first, new_hi)

    def rebuild(self, window: int, tau_max: int, forgetting: float) -> None:
        """New W / tau_max / lambda: keep the newest samples, recompute the sums from them."""
        keep = min(self.stored, window, self.count - self.window_start)
        v, y = self.v[self.stored - keep : self.stored].copy(), self.y[self.stored - keep : self.stored].copy()
        self.__init__(window, tau_max, forgetting)
        self.add(v, y)

    def raw(self) -> tuple[np.ndarray, np.ndarray]:
        s = self._local(self.window_start, self.count)
        return self.v[s].copy(), self.y[s].copy()

    def correlations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        scale = 1.0 / self.weight if self.weight > 0 else 0.0
        sums = self.window_sums()
        return sums[0] * scale, sums[1] * scale, sums[2] * scale


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
        self._anchor: float | None = None
        self._k = 0
        self._last_grid = -np.inf
        self._segment_samples = 0

    def regrid(self, config: EngineConfig) -> None:
        """A new sample_rate: the grid restarts at the next excitation sample (0 = keep the old
        rate as the estimate behind the tolerances)."""
        self.config = config
        self.rate = config.sample_rate or self.rate
        self.stats.sample_rate = self.rate or 0.0
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
        return stamp - period * np.arange(count - 1, -1, -1)

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
        pending buffer while the other stream's batch waits. Returns the samples accepted."""
        piece = self.pending_cap // 4
        heads = {name: 0 for name in batches}
        accepted = 0
        while heads:
            def behind(name: str) -> float:
                t = batches[name][0]
                return float(t[heads[name]]) if np.isfinite(t[heads[name]]) else -np.inf

            name = min(heads, key=behind)
            t, x = batches[name]
            start = heads[name]
            stop = min(t.size, start + piece)
            accepted += self.add(name, t[start:stop], x[start:stop])
            if stop >= t.size:
                del heads[name]
            else:
                heads[name] = stop
        return accepted

    def _count_received(self, stream: str, n: int) -> None:
        if stream == "excitation":
            self.stats.received_excitation += n
        else:
            self.stats.received_response += n

    def add(self, stream: str, t, x) -> int:
        """Screen and add samples x at stamps t (s) to ``stream``; returns how many were accepted."""
        t = np.atleast_1d(np.asarray(t, dtype=float)).ravel()
        x = np.atleast_1d(np.asarray(x, dtype=float)).ravel()
        if t.size != x.size:
            raise ValueError(f"{stream}: {t.size} stamps for {x.size} samples")
        self._count_received(stream, x.size)
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(t) & np.isfinite(x) & (np.abs(x) <= MAX_ABS_SAMPLE)
        self.stats.nan_skipped += int(x.size - finite.sum())
        self.stats.bad_values[stream] += int(np.count_nonzero(~finite & np.isfinite(t)))
        return self._add_screened(stream, t[finite], x[finite])

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
        s = self._streams[stream]
        accept = t > newest
        self.stats.duplicate += int(np.count_nonzero(t == newest))
        self.stats.late += int(np.count_nonzero(t < newest))
        t, x = t[accept], x[accept]
        if t.size == 0:
            return 0
        self.stats.accepted[stream] += t.size
        self.stats.first_stamp.setdefault(stream, float(t[0]))
        self.stats.last_stamp[stream] = float(t[-1])
        self.stats.overflow += s.append(t, x, cap=self.pending_cap)
        self._emit()
        return int(t.size)

    def _infer_rate(self) -> None:
        t = self._streams["excitation"].t
        if t.size >= INFER_SAMPLES:
            self.rate = float(1.0 / np.median(np.diff(t[:INFER_SAMPLES])))
            self.stats.sample_rate = self.rate

    def _next_grid_time(self, ex: _Stream, start: float, tol: float) -> float | None:
        """The first grid point not yet emitted and not before ``start`` (None: wait for data)."""
        if self.config.sample_rate:  # fixed grid t_a + k / fs
            if self._anchor is None:
                self._anchor, self._k = float(ex.t[0]), 0
            self._k = max(self._k, math.ceil((start - tol - self._anchor) * self.rate))
            return self._anchor + self._k / self.rate
        later = ex.t[(ex.t > self._last_grid) & (ex.t >= start - tol)]  # excitation-clocked grid
        return float(later[0]) if later.size else None

    def _grid_until(self, ex: _Stream, first: float, end: float) -> np.ndarray:
        if self.config.sample_rate:
            last_k = math.floor((end - self._anchor) * self.rate)
            return self._anchor + np.arange(self._k, last_k + 1) / self.rate
        return ex.t[(ex.t >= first) & (ex.t <= end)]

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
            tk = self._next_grid_time(ex, max(ex.t[0], re.t[0]), tol)
            if tk is None:
                return
            ends = {}
            for name, s in (("excitation", ex), ("response", re)):
                index = int(np.searchsorted(s.t, tk + tol, side="right")) - 1
                ends[name] = s.segment_end(max(index, 0), max_gap)
            end = min(e for e, _ in ends.values())
            grid = self._grid_until(ex, tk, end + tol)
            if grid.size:
                self._emit_grid(grid, ex.values_at(grid, tol, cfg.interpolation),
                                re.values_at(grid, tol, cfg.interpolation))
                for s in (ex, re):  # keep the last sample at or before the newest grid point
                    s.drop(max(0, int(np.searchsorted(s.t, grid[-1] + tol, side="right")) - 1))
            blocked = [(name, resume) for name, (e, resume) in ends.items() if resume is not None and e <= end]
            if not blocked:
                return
            name, resume = blocked[0]
            s = self._streams[name]
            s.drop(int(np.searchsorted(s.t, resume, side="left")))
            if name == "excitation":
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


class StreamingEngine:
    """Aligns excitation and response streams, keeps the correlation sums and the raw window."""

    def __init__(self, config: EngineConfig | None = None) -> None:
        self._config = (config or EngineConfig()).validated()
        self.stats = EngineStats(sample_rate=self._config.sample_rate)
        self._corr = _CorrelationWindow(self._config.window, self._config.tau_max, self._config.forgetting)
        self._aligner = StreamAligner(self._config, self.stats, self._append_aligned, self._corr.reset)
        self._stamp = float("nan")
        self._published: IdentificationResult | None = None
        self._reference_std = 0.0

    @property
    def config(self) -> EngineConfig:
        return self._config

    @property
    def sample_rate(self) -> float | None:
        """Grid rate in Hz (configured or inferred), None while still inferring."""
        return self._aligner.rate

    # ---------------------------------------------------------------- configuration
    def reconfigure(self, **changes) -> None:
        """Apply validated changes live. window / tau_max / forgetting rebuild the sums from the
        raw window (no sample is lost); sample_rate re-grids (the window restarts, since samples
        at two rates cannot share lag products); other fields only affect the next solve."""
        names = {f.name for f in fields(EngineConfig)}
        for name in changes:
            if name not in names:
                raise UsageError(f"{name}: unknown engine setting (known: {', '.join(sorted(names))})")
        if "partition" in changes and changes["partition"] is not None:
            changes["partition"] = tuple(float(c) for c in changes["partition"])
        new = replace(self._config, **changes).validated()
        old, self._config = self._config, new
        self._published, self._reference_std = None, 0.0  # new settings: the next estimate is published
        self._aligner.config = new
        if (new.window, new.tau_max, new.forgetting) != (old.window, old.tau_max, old.forgetting):
            self._corr.rebuild(new.window, new.tau_max, new.forgetting)
        if new.sample_rate != old.sample_rate:
            self._corr.reset()
            self._aligner.regrid(new)
        self._update_fill()

    # ---------------------------------------------------------------- ingestion
    def add_excitation(self, t: np.ndarray, v: np.ndarray) -> int:
        """Add samples v at stamps t (s); returns how many were accepted."""
        return self._aligner.add("excitation", t, v)

    def add_response(self, t: np.ndarray, y: np.ndarray) -> int:
        """Add samples y at stamps t (s); returns how many were accepted."""
        return self._aligner.add("response", t, y)

    def message_stamps(self, stream: str, stamp: float, count: int) -> np.ndarray | None:
        """See ``StreamAligner.message_stamps`` (batch convention: last sample at the stamp)."""
        return self._aligner.message_stamps(stream, stamp, count)

    def add_message(self, stream: str, stamp: float, values: np.ndarray, flush: bool = True) -> int:
        """Add one message's samples of ``stream`` ("excitation" or "response"); with
        ``flush=False`` buffer them until ``flush()`` (see ``StreamAligner.add_message``)."""
        return self._aligner.add_message(stream, stamp, values, flush)

    def flush(self) -> int:
        """Add the messages buffered with ``add_message(..., flush=False)``."""
        return self._aligner.flush()

    def add_streams(self, batches: dict[str, tuple[np.ndarray, np.ndarray]]) -> int:
        """Add (stamps, values) of both streams at once, interleaved in time (``StreamAligner.add_both``)."""
        return self._aligner.add_both(batches)

    @property
    def buffered(self) -> int:
        """Samples buffered by ``add_message(..., flush=False)`` and not yet flushed."""
        return self._aligner.buffered

    def _append_aligned(self, grid: np.ndarray, v: np.ndarray, y: np.ndarray) -> None:
        self._corr.add(v, y)
        self._stamp = float(grid[-1])
        self._update_fill()

    def _update_fill(self) -> None:
        n = self._corr.count - self._corr.window_start
        self.stats.window_samples = n
        self.stats.window_fill = n / self._config.window

    # ---------------------------------------------------------------- solving
    def snapshot(self) -> EngineSnapshot:
        v, y = self._corr.raw()
        phi_vv, phi_yv, phi_yvv = self._corr.correlations()
        return EngineSnapshot(self._config, phi_vv, phi_yv, phi_yvv, self._corr.weight, v, y, self._stamp,
                              self.stats.copy(), self._published, self._reference_std)

    def solve(self) -> SolveOutcome:
        """Solve on the current window (synchronously) and count it in the stats."""
        outcome = solve_snapshot(self.snapshot())
        self.record(outcome)
        return outcome

    def record(self, outcome: SolveOutcome) -> None:
        """Count a solve (done here or in a worker thread) in the stats."""
        if outcome.ok:
            self.stats.solves += 1
            self._published = outcome.result
            self._reference_std = max(self._reference_std, outcome.input_std)
            return
        self.stats.solve_errors += 1
        if outcome.status == "not_exciting":
            self.stats.not_exciting += 1
        elif outcome.status == "kept":
            self.stats.kept_published += 1
        elif outcome.status == "failed":
            self.stats.solve_failures += 1
        elif outcome.status == "exception":
            self.stats.solve_exceptions += 1


def excitation_condition_number(phi_vv: np.ndarray, tau_max: int, order: int) -> float:
    """cond(R_p) of the input autocorrelation (Toeplitz) matrix R_p = [phi_vv(i - j)], p = 2n + 1
    (capped at tau_max + 1): the input is persistently exciting of order p when R_p is well
    conditioned (Ljung, System Identification, sec. 13.2). Uncentred, so a constant input gives a
    rank-one R_p; a sinusoid is exciting of order 2 only, a sum of s sinusoids of order 2s."""
    p = min(2 * order + 1, tau_max + 1)
    one_sided = 0.5 * (phi_vv[tau_max : tau_max + p] + phi_vv[tau_max::-1][:p])
    idx = np.arange(p)
    eig = np.linalg.eigvalsh(one_sided[np.abs(idx[:, None] - idx[None, :])])
    if eig[-1] <= 0 or eig[0] <= eig[-1] * 1e-300:
        return float("inf")
    return float(eig[-1] / eig[0])


def solve_snapshot(snapshot: EngineSnapshot) -> SolveOutcome:
    """Identify the configured model on a snapshot (pure; may run in a worker thread).

    CLS (paper 000 sec. 3.1): step 1 on the snapshot's correlation sums, step 2 on the raw
    window; other methods: ``methods.identify`` on the raw window. Not ok (with the reason) when
    the window is not ``min_fill`` full, the input is not persistently exciting or the method
    fails on the data."""
    started = time.perf_counter()
    cfg, v, y = snapshot.config, snapshot.v, snapshot.y

    spread = float("nan")

    def outcome(ok, reason, result=None, doc=None, cond=float("nan"), status="ok") -> SolveOutcome:
        return SolveOutcome(ok, reason, result, doc, cond, time.perf_counter() - started, int(v.size), snapshot.stamp,
                            status, spread)

    needed = max(math.ceil(cfg.min_fill * cfg.window), 2 * cfg.tau_max + 2)
    if v.size < needed or snapshot.weight <= 0:
        return outcome(False, f"window {100 * v.size / cfg.window:.0f} % full (need {needed} samples)",
                       status="filling")
    with np.errstate(all="ignore"):
        cond = excitation_condition_number(snapshot.phi_vv, cfg.tau_max, cfg.order)
    spread = float(np.std(v))
    if spread <= 1e-12 * max(1.0, float(np.max(np.abs(v)))) or not cond <= PE_CONDITION_LIMIT:
        return outcome(False, f"not persistently exciting (input std {spread:.3g}, condition number {cond:.3g})",
                       cond=cond, status="not_exciting")
    reference = snapshot.reference_std
    if spread < cfg.min_excitation * reference:
        return outcome(False, f"not persistently exciting (input std {spread:.3g} is {100 * spread / reference:.1f} % "
                              f"of the {reference:.3g} behind the published model, min_excitation "
                              f"{cfg.min_excitation:g})", cond=cond, status="not_exciting")
    try:
        with np.errstate(all="ignore"):  # an unstable early model: fit/rms become null, no warning
            if cfg.method in CLS_STRUCTURES:
                from .correlation_least_squares import cls_from_correlations

                result = cls_from_correlations(snapshot.phi_vv, snapshot.phi_yv, v, y, cfg.identify_options(),
                                               structure=CLS_STRUCTURES[cfg.method])
            else:
                result = identify(cfg.method, v, y, cfg.identify_options())
            doc = result.to_json(v, y)
            kept = _published_fits_better(snapshot.published, v, y, doc.get("fit_percent"))
    except (HammerRosError, np.linalg.LinAlgError, ValueError) as exc:
        return outcome(False, f"{cfg.method}: {exc}", cond=cond, status="failed")
    except Exception as exc:  # a bug in a method must not stop the node: reported, counted, never fatal
        return outcome(False, f"{cfg.method}: internal error {type(exc).__name__}: {exc}", cond=cond,
                       status="exception")
    finite = np.all(np.isfinite(result.linear.a)) and np.all(np.isfinite(result.linear.b))
    if not finite:
        return outcome(False, f"{cfg.method}: non-finite model coefficients", cond=cond, status="failed")
    if kept:
        return outcome(False, f"kept the published model: it fits the window better ({kept})", cond=cond,
                       status="kept")
    return outcome(True, "", result, doc, cond)


def _published_fits_better(published: IdentificationResult | None, v: np.ndarray, y: np.ndarray,
                           new_fit: float | None) -> str:
    """'' or why the published model stays: on a window that says little (a fading excitation,
    noise), a new estimate can be far off; it replaces the published model unless the published
    model simulates the window better by more than KEEP_MARGIN fit points."""
    if published is None:
        return ""
    old_fit = fit_percent(y, published.simulate(v))
    new = -np.inf if new_fit is None else new_fit
    if not np.isfinite(old_fit) or new >= old_fit - KEEP_MARGIN:
        return ""
    return f"fit {old_fit:.1f} % vs {new:.1f} % for the new estimate"
