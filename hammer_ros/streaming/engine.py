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
   chunk: one C correlation loop per row, or real FFTs where cheaper: ``by_fft``) into a block
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
   better (``kept``), when its bounds are too wide or its ``warnings`` say not to trust it
   (``poor_fit``, ``not_exciting``: ``identification.trust``; both ``uncertain``), or when the
   method fails or raises (never propagated).
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, fields, replace

import numpy as np

from ..errors import HammerRosError, UsageError
from ..identification.compiled_loops import spread_figures, toeplitz_condition
from ..identification.instrumental import refinement_input
from ..identification.methods import identify
from ..identification.result import IdentificationResult
from ..identification.trust import ModelWarning, untrusted
from .aligner import StreamAligner
from .config import CLS_STRUCTURES, KEEP_MARGIN, PE_CONDITION_LIMIT, EngineConfig, EngineStats
from .correlation_window import CorrelationWindow
from .reference import ReferenceTrack


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
    epoch: int = 0  # changes when the published model is forgotten (new engine, new settings): ``SolverProcess``
    reference_window: np.ndarray | None = None  # a closed loop's reference on the window's grid (NaN: none there)

    def __reduce__(self):
        """Pickled with its five arrays as the bytes of one (a ``SolverProcess`` sends a snapshot per
        solve: about half the time of pickling and unpickling five numpy arrays)."""
        arrays = [np.asarray(x, dtype=float).ravel() for x in (self.phi_vv, self.phi_yv, self.phi_yvv, self.v, self.y)]
        return (_unpacked_snapshot, (np.concatenate(arrays).tobytes(), tuple(x.size for x in arrays), self.config,
                                     self.weight, self.stamp, self.stats, self.published, self.reference_std,
                                     self.epoch, self.reference_window))


def _unpacked_snapshot(packed: bytes, sizes: tuple[int, ...], config: EngineConfig, weight: float,
                       *rest) -> EngineSnapshot:
    """``EngineSnapshot.__reduce__``'s inverse: the arrays as writable slices of one copy of ``packed``."""
    values, arrays, start = np.frombuffer(packed).copy(), [], 0
    for size in sizes:
        arrays.append(values[start : start + size])
        start += size
    phi_vv, phi_yv, phi_yvv, v, y = arrays
    stamp, stats, published, reference_std, epoch, reference_window = rest
    return EngineSnapshot(config, phi_vv, phi_yv, phi_yvv, weight, v, y, stamp, stats, published, reference_std, epoch,
                          reference_window)



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
    status: str = "ok"  # ok | filling | not_exciting | kept | uncertain | failed (method rejected the data) | exception
    input_std: float = float("nan")  # of the window's input
    markov: tuple[float, ...] = ()  # the model's first 2n + 1 Markov parameters (ok outcomes)



_EPOCHS = itertools.count(1)


class StreamingEngine:
    """Aligns excitation and response streams, keeps the correlation sums and the raw window."""

    def __init__(self, config: EngineConfig | None = None, reference: bool = False) -> None:
        """``reference``: also take a closed loop's reference (``add_reference``), the instrument of
        every solve (``identification.instrumental``)."""
        self._config = (config or EngineConfig()).validated()
        self.stats = EngineStats(sample_rate=self._config.sample_rate)
        self._corr = CorrelationWindow(self._config.window, self._config.tau_max, self._config.forgetting)
        self._aligner = StreamAligner(self._config, self.stats, self._append_aligned, self._corr.reset)
        self._stamp = float("nan")
        self._published: IdentificationResult | None = None
        self._undocumented: tuple[SolveOutcome, np.ndarray, np.ndarray] | None = None  # ``solve(document=False)``
        self._reference_std = 0.0
        self._epoch = next(_EPOCHS)
        self._reference = ReferenceTrack(self._config.window) if reference else None

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
        self._epoch = next(_EPOCHS)
        self._aligner.config = new
        if self._reference is not None:
            self._reference.capacity = max(self._reference.capacity, new.window)
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

    def add_reference(self, t: np.ndarray, r: np.ndarray) -> None:
        """Add reference samples r at stamps t (s) (an engine made with ``reference=True``)."""
        self._reference.add(t, r)

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
        if self._reference is not None:
            self._reference.grid(grid)
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
        reference = None
        if self._reference is not None:
            rate = self._aligner.rate or 1.0
            gap = self._config.max_gap or 5.0 / rate
            reference = self._reference.window(v.size, 0.01 / rate, gap)
        return EngineSnapshot(self._config, phi_vv, phi_yv, phi_yvv, self._corr.weight, v, y, self._stamp,
                              self.stats.copy(), self._published, self._reference_std, self._epoch, reference)

    def solve(self, document: bool = True) -> SolveOutcome:
        """Solve on the current window (synchronously) and count it in the stats. ``document=False``:
        an ok outcome without ``doc`` and ``markov`` (``solve_snapshot``), for an owner that reads
        only the last good model's document: ``documented`` adds them to it afterwards."""
        snapshot = self.snapshot()
        outcome = solve_snapshot(snapshot, document)
        self.record(outcome)
        if outcome.ok and not document:
            self._undocumented = (outcome, snapshot.v, snapshot.y)
        return outcome

    def documented(self, outcome: SolveOutcome) -> SolveOutcome:
        """The ok outcome of this engine's last ok ``solve(document=False)`` with the ``doc`` and
        ``markov`` that ``document=True`` gives (``document_outcome`` on its window); any other outcome
        as it is."""
        if outcome.doc is not None or self._undocumented is None or self._undocumented[0] is not outcome:
            return outcome
        return document_outcome(outcome, *self._undocumented[1:])

    def record(self, outcome: SolveOutcome) -> None:
        """Count a solve (done here, in a worker thread or in a ``SolverProcess``) in the stats;
        an ok outcome becomes the published model."""
        count_outcome(self.stats, outcome)
        if outcome.ok:
            self._published = outcome.result
            self._reference_std = max(self._reference_std, outcome.input_std)


def count_outcome(stats: EngineStats, outcome: SolveOutcome) -> None:
    """The counters of ``stats`` that one solve moves."""
    if outcome.ok:
        stats.solves += 1
        return
    stats.solve_errors += 1
    if outcome.status == "not_exciting":
        stats.not_exciting += 1
    elif outcome.status == "kept":
        stats.kept_published += 1
    elif outcome.status == "uncertain":
        stats.uncertain += 1
    elif outcome.status == "failed":
        stats.solve_failures += 1
    elif outcome.status == "exception":
        stats.solve_exceptions += 1



def excitation_condition_number(phi_vv: np.ndarray, tau_max: int, order: int) -> float:
    """cond(R_p) of the input autocorrelation (Toeplitz) matrix R_p = [phi_vv(i - j)], p = 2n + 1
    (capped at tau_max + 1): the input is persistently exciting of order p when R_p is well
    conditioned (Ljung, System Identification, sec. 13.2). Uncentred, so a constant input gives a
    rank-one R_p; a sinusoid is exciting of order 2 only, a sum of s sinusoids of order 2s."""
    return toeplitz_condition(phi_vv, tau_max, min(2 * order + 1, tau_max + 1))



@dataclass(frozen=True, eq=False)
class Estimate:
    """What a solve computes from the window alone (``estimate_snapshot``): the input's
    excitation figures, and the method's model with its fit on the window (``result`` None when
    a check stopped the solve before the method, ``status`` failed / exception when the method
    did). ``decide_outcome`` makes the outcome of it with the published model and reference std
    of the solve's turn. Picklable for the CLS methods (``SolverProcess``: the owner may estimate
    a snapshot itself, the worker decides)."""

    condition_number: float  # nan while filling
    input_std: float
    input_peak: float  # max |v|
    result: IdentificationResult | None = None
    doc: dict | None = None
    fit: float | None = None  # the model's fit percent on the window (None: not finite)
    warnings: tuple[ModelWarning, ...] = ()  # the model's own on the window (``trust.model_warnings``; not
    # ``input_not_white`` when not documented: the outcome reads the UNTRUSTED ones)
    status: str = ""  # '' (a model, or stopped by a check) | failed | exception
    reason: str = ""
    seconds: float = 0.0


def window_problem(snapshot: EngineSnapshot) -> tuple[str, str, float, float]:
    """(status, reason, condition number, input std) of the checks before a solve: status
    ``filling`` (the window is not ``min_fill`` full) or ``not_exciting`` (the input is not
    persistently exciting, absolutely or relative to the published models), '' when a solve can
    be tried."""
    cond, spread, peak = _excitation(snapshot)
    return (*_window_status(snapshot, cond, spread, peak), cond, spread)


def _needed_samples(snapshot: EngineSnapshot) -> int:
    """The samples a solve needs, 0 when the window has them (its correlation sums are not empty)."""
    cfg = snapshot.config
    needed = max(math.ceil(cfg.min_fill * cfg.window), 2 * cfg.tau_max + 2)
    return needed if snapshot.v.size < needed or snapshot.weight <= 0 else 0


def _excitation(snapshot: EngineSnapshot) -> tuple[float, float, float]:
    """(condition number, std, max |v|) of the window's input; nan while it fills."""
    cfg, v = snapshot.config, snapshot.v
    if _needed_samples(snapshot):
        return math.nan, math.nan, math.nan
    with np.errstate(all="ignore"):
        cond = excitation_condition_number(snapshot.phi_vv, cfg.tau_max, cfg.order)
    spread, high, low, _ = spread_figures(v)  # np.std to rounding
    return cond, spread, max(high, -low)


def _window_status(snapshot: EngineSnapshot, cond: float, spread: float, peak: float) -> tuple[str, str]:
    """(status, reason) of ``window_problem`` from the figures of ``_excitation`` and the
    snapshot's reference std."""
    cfg, v = snapshot.config, snapshot.v
    if needed := _needed_samples(snapshot):
        return "filling", f"window {100 * v.size / cfg.window:.0f} % full (need {needed} samples)"
    if spread <= 1e-12 * max(1.0, peak) or not cond <= PE_CONDITION_LIMIT:
        return "not_exciting", f"not persistently exciting (input std {spread:.3g}, condition number {cond:.3g})"
    reference = snapshot.reference_std
    if spread < cfg.min_excitation * reference:
        return ("not_exciting", f"not persistently exciting (input std {spread:.3g} is "
                f"{100 * spread / reference:.1f} % of the {reference:.3g} behind the published model, "
                f"min_excitation {cfg.min_excitation:g})")
    return "", ""


def solve_snapshot(snapshot: EngineSnapshot, document: bool = True) -> SolveOutcome:
    """Identify the configured model on a snapshot (pure; may run in a worker thread):
    ``decide_outcome`` of ``estimate_snapshot``.

    CLS (paper 000 sec. 3.1): step 1 on the snapshot's correlation sums, step 2 on the raw
    window; other methods: ``methods.identify`` on the raw window. Not ok (with the reason) when
    the window is not ``min_fill`` full, the input is not persistently exciting, the method
    fails on the data or the published model fits the window clearly better. ``document=False``:
    an ok outcome without ``doc`` and ``markov`` (what only the outputs read; ``document_outcome``
    adds them): the model's fit on the window, which the choice against the published model
    needs, is computed alone."""
    return decide_outcome(snapshot, estimate_snapshot(snapshot, document), document)


def estimate_snapshot(snapshot: EngineSnapshot, document: bool = True) -> Estimate:
    """The part of ``solve_snapshot`` that needs the window only: the excitation checks (with
    the snapshot's reference std: a smaller one than the solve's turn has only lets more windows
    through) and, when they pass, the method's model and its fit (``doc`` with ``document``)."""
    started = time.perf_counter()
    cfg, v, y = snapshot.config, snapshot.v, snapshot.y
    cond, spread, peak = _excitation(snapshot)

    def estimate(**found) -> Estimate:
        return Estimate(cond, spread, peak, seconds=time.perf_counter() - started, **found)

    if _window_status(snapshot, cond, spread, peak)[0]:
        return estimate()
    reference = snapshot.reference_window
    if reference is not None and not np.all(np.isfinite(reference)):
        missing = int(np.count_nonzero(~np.isfinite(reference)))
        return estimate(status="failed", reason=f"reference: none at {missing} of the window's {reference.size} "
                        "samples (before its first sample or in a gap)")
    try:
        with np.errstate(all="ignore"):  # an unstable early model: fit/rms become null, no warning
            if reference is not None:  # closed loop: the methods' instrumented forms on the raw window
                result = identify(cfg.method, v, y, replace(cfg.identify_options(), reference=reference))
            elif cfg.method in CLS_STRUCTURES:
                from ..identification.correlation_least_squares import cls_from_correlations

                result = cls_from_correlations(snapshot.phi_vv, snapshot.phi_yv, v, y, cfg.identify_options(),
                                               structure=CLS_STRUCTURES[cfg.method])
            else:
                result = identify(cfg.method, v, y, cfg.identify_options())
            if cfg.refine:
                from ..identification.refinement import refine_result

                result = refine_result(result, refinement_input(v, reference), y)
            evaluation = result.evaluate(v, y, input_assumptions=document,  # the outcome reads UNTRUSTED ones only
                                         compiled=True)
            doc = result.to_json(v, y, evaluation=evaluation) if document else None
    except Exception as exc:  # a bug in a method must not stop the node: reported, counted, never fatal
        status, reason = _failure(cfg.method, exc)
        return estimate(status=status, reason=reason)
    fit = evaluation.fit if math.isfinite(evaluation.fit) else None
    return estimate(result=result, doc=doc, fit=fit, warnings=evaluation.warnings)


def _failure(method: str, exc: Exception) -> tuple[str, str]:
    """(status, reason) of an exception in a solve: ``failed`` when the method rejected the data
    (HammerRosError, LinAlgError, ValueError), ``exception`` for anything else (a bug: reported,
    counted, never fatal)."""
    if isinstance(exc, (HammerRosError, np.linalg.LinAlgError, ValueError)):
        return "failed", f"{method}: {exc}"
    return "exception", f"{method}: internal error {type(exc).__name__}: {exc}"


def portable_estimate(config: EngineConfig) -> bool:
    """Whether the estimates of ``config``'s method can cross the pipe to a ``SolverProcess`` (CLS
    without refinement: its results simulate through a partial), i.e. may be made in one process
    and decided in another."""
    return config.method in CLS_STRUCTURES and not config.refine


def decide_outcome(snapshot: EngineSnapshot, estimate: Estimate, document: bool = True) -> SolveOutcome:
    """The outcome of ``estimate`` (of this snapshot's window, by ``estimate_snapshot`` with the
    same ``document``) with the snapshot's published model and reference std: not exciting
    relative to the reference, failed, kept (the published model fits the window clearly
    better) or ok. An estimate stopped by a check that the snapshot's reference std passes (a
    larger reference was behind it) is estimated again here."""
    started = time.perf_counter()
    cfg, v, y = snapshot.config, snapshot.v, snapshot.y
    cond, spread = estimate.condition_number, estimate.input_std
    status, reason = _window_status(snapshot, cond, spread, estimate.input_peak)
    if not status and not estimate.status and estimate.result is None:
        return decide_outcome(snapshot, estimate_snapshot(snapshot, document), document)

    def outcome(ok, reason, result=None, doc=None, status="ok", markov=()) -> SolveOutcome:
        return SolveOutcome(ok, reason, result, doc, cond, estimate.seconds + time.perf_counter() - started,
                            int(v.size), snapshot.stamp, status, spread, markov)

    if status:
        return outcome(False, reason, status=status)
    if estimate.status:
        return outcome(False, estimate.reason, status=estimate.status)
    result = estimate.result
    try:
        with np.errstate(all="ignore"):  # closed loop: no keeping (below)
            kept = "" if snapshot.reference_window is not None else _published_fits_better(
                snapshot.published, v, y, estimate.fit)
    except Exception as exc:
        status, reason = _failure(cfg.method, exc)
        return outcome(False, reason, status=status)
    if not all(map(math.isfinite, result.linear.a.tolist() + result.linear.b.tolist())):
        return outcome(False, f"{cfg.method}: non-finite model coefficients", status="failed")
    if kept:
        return outcome(False, f"kept the published model: it fits the window better ({kept})", status="kept")
    wide = too_uncertain(result, cfg.max_relative_sd)
    if wide:
        return outcome(False, f"uncertain model: {wide}", status="uncertain")
    closed = snapshot.reference_window is not None  # the free-run fit on v is the noise fed back: no poor_fit
    doubt = untrusted(w for w in estimate.warnings if not (closed and w.code == "poor_fit"))
    if doubt is not None:  # poor_fit, not_exciting: never published as a confident model
        return outcome(False, f"uncertain model: {doubt.code}: {doubt.message}", status="uncertain")
    return outcome(True, "", result, estimate.doc, markov=_markov(result, estimate.doc) if document else ())


def too_uncertain(result: IdentificationResult, max_relative_sd: float) -> str:
    """'' or why the model's bounds are too wide to publish it (``max_relative_sd`` 0: never): a pole
    whose 95 % interval of the modulus, |p| +- 1.96 sd(|p|), crosses the unit circle (sd(|p|) to first
    order sqrt((re sd_re)^2 + (im sd_im)^2) / |p|), a pole's sd above ``max_relative_sd`` x the larger
    of |p| and 1 - |p| (a fast pole near 0 is measured against the unit circle, not against its own
    small modulus), or the gain's sd above ``max_relative_sd`` x |gain|. The last confident model
    then stays, marked stale."""
    bounds = result.uncertainty
    if bounds is None or max_relative_sd <= 0:
        return ""
    for pole, (sd_re, sd_im) in zip(result.poles.tolist(), np.asarray(bounds.poles_std).tolist(), strict=True):
        radius = abs(pole)
        sd = math.hypot(pole.real * sd_re, pole.imag * sd_im) / radius if radius > 0 else math.hypot(sd_re, sd_im)
        if not math.isfinite(sd) or (radius - 1.0) * (radius - 1.0) <= (1.96 * sd) ** 2:
            return f"the 95 % interval of pole {pole:.4g} (|p| {radius:.4g} +- {1.96 * sd:.2g}) crosses the unit circle"
        if math.hypot(sd_re, sd_im) > max_relative_sd * max(radius, 1.0 - radius):
            return (f"pole {pole:.4g} has sd {math.hypot(sd_re, sd_im):.2g} > max_relative_sd {max_relative_sd:g} "
                    f"x max(|p|, 1 - |p|)")
    if bounds.gain_std is not None and result.gain is not None and bounds.gain_std > max_relative_sd * abs(result.gain):
        return f"gain {result.gain:.4g} has sd {bounds.gain_std:.2g} > max_relative_sd {max_relative_sd:g} x |gain|"
    return ""


def document_outcome(outcome: SolveOutcome, v: np.ndarray, y: np.ndarray) -> SolveOutcome:
    """An ok outcome of ``solve_snapshot(..., document=False)`` on the window (v, y) with the
    ``doc`` and ``markov`` that ``document=True`` gives."""
    with np.errstate(all="ignore"):
        doc = outcome.result.to_json(v, y, evaluation=outcome.result.evaluate(v, y, compiled=True))
    return replace(outcome, doc=doc, markov=_markov(outcome.result, doc))


def _markov(result: IdentificationResult, doc: dict) -> tuple[float, ...]:
    """The model's first 2n + 1 Markov parameters (the method's own when its document has them)."""
    markov = doc.get("markov")
    if markov is None:
        markov = result.linear.markov_parameters(2 * result.linear.order + 1).tolist()
    return tuple(map(float, markov))



def _published_fits_better(published: IdentificationResult | None, v: np.ndarray, y: np.ndarray,
                           new_fit: float | None) -> str:
    """'' or why the published model stays: on a window that says little (a fading excitation,
    noise), a new estimate can be far off; it replaces the published model unless the published
    model simulates the window better by more than KEEP_MARGIN fit points. Not with a closed
    loop's reference: there the free-run fit on v is the noise fed back, and a biased model may
    simulate it better than the instrumented one."""
    if published is None:
        return ""
    old_fit = published.window_fit(v, y)[0]
    new = -np.inf if new_fit is None or not math.isfinite(new_fit) else new_fit
    if not np.isfinite(old_fit) or new >= old_fit - KEEP_MARGIN:
        return ""
    return f"fit {old_fit:.1f} % vs {new:.1f} % for the new estimate"
