"""The engine's configuration (the node's parameters), its counters and its resource limits."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from ..errors import UsageError
from ..identification.methods import METHODS, IdentifyOptions

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
HOLD_PERIODS = 4.0  # an excitation whose median step is longer than this many grid periods is held (aligner)
SPARSE_RESPONSE = 1.5  # a response whose median step exceeds this many grid periods is interpolated linearly
_FIELD_KINDS = {"sample_rate": float, "window": int, "forgetting": float, "tau_max": int, "method": str, "order": int,
                "delay": int, "mu": int, "poly": int, "partition": tuple, "interpolation": str, "max_gap": float,
                "min_fill": float, "min_excitation": float, "refine": bool, "max_relative_sd": float}


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
    refine: bool = False  # refine each solve's estimate on the simulation error (identification.refinement)
    max_relative_sd: float = 0.25  # pole sd / max(|p|, 1 - |p|), gain sd / |gain| above: uncertain; 0 = off

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
            if kind is bool and not isinstance(value, (bool, np.bool_)):
                raise bad(f.name, "must be true or false")
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
        if not (math.isfinite(self.max_relative_sd) and self.max_relative_sd >= 0):
            raise bad("max_relative_sd", "must be >= 0 (0 = off)")
        return self

    def identify_options(self) -> IdentifyOptions:
        return IdentifyOptions(order=self.order, delay=self.delay, mu=self.mu, poly=self.poly,
                               partition=self.partition, tau_max=self.tau_max)



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
    excitation_held: bool = False  # the excitation publishes far below the grid rate: held between messages
    solves: int = 0
    solve_errors: int = 0  # solves that gave no model, for any reason below or the window filling
    not_exciting: int = 0  # ... because the input was not persistently exciting
    kept_published: int = 0  # ... because the published model fits the window clearly better
    uncertain: int = 0  # ... because the new model's bounds are wide (``engine.too_uncertain``)
    solve_failures: int = 0  # ... because the method failed on the data (e.g. an empty PLLS interval)
    solve_exceptions: int = 0  # ... because of an unexpected exception (logged; ingestion goes on)
    first_stamp: dict = field(default_factory=dict)  # stream -> first accepted stamp
    last_stamp: dict = field(default_factory=dict)  # stream -> newest accepted stamp
    accepted: dict = field(default_factory=lambda: {s: 0 for s in STREAMS})
    bad_values: dict = field(default_factory=lambda: {s: 0 for s in STREAMS})  # finite stamp, non-finite value

    def missing(self, stream: str) -> int:
        """Samples of ``stream`` that the stamps say were sent but never arrived (a uniform
        stream at ``sample_rate`` since its first stamp, or the last clock reset; 0 while the
        rate is unknown, and for a held excitation): what the middleware dropped before the node saw it."""
        span = self.last_stamp.get(stream, 0.0) - self.first_stamp.get(stream, 0.0)
        held = stream == "excitation" and self.excitation_held
        if not self.sample_rate or stream not in self.first_stamp or held:
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
        """A copy (its dicts copied too; without ``replace``'s __init__, a quarter of its time: one per solve)."""
        copied = object.__new__(EngineStats)
        copied.__dict__.update(self.__dict__, first_stamp=dict(self.first_stamp), last_stamp=dict(self.last_stamp),
                               accepted=dict(self.accepted), bad_values=dict(self.bad_values))
        return copied
