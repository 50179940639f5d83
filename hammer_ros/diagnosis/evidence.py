"""The tests that tell the causes apart.

Each cause leaves its own first-order signature in the baseline's simulation error e = y - x
(x the baseline's free-run output, F its map, G its linear block, v the input):

| cause | e is, to first order, a combination of |
|---|---|
| output_nonlinearity | static functions of x: hinges (x - k_j)_+ at quantiles of x |
| output_feedback | the same hinges passed through G: G[(x - k_j)_+] (y = G[F(v) - h(y)]) |
| output_feedback (servo) | G[hinges of the loop error v - x and of dx] beyond those: y = G[f(v - y) - h(y) - phi(dy)] |
| parallel_path | linear dynamics of v itself: lags 0..11 and first-order filters of v |
| unmodeled_dynamics | linear dynamics of F(v): lags 0..11 and first-order filters of F(v) |
| backlash | G[F'(v) s], s = sign of the last input change (play shifts v by -w/2 s) |
| input_dynamics | G[F'(v) (L_p - 1) v], beyond G[hinges of v] (a filter L ahead: F(Lv) ~ F(v) + F'(v)(L - 1)v) |
| parallel_path (i.i.d. input) | first- and second-order input-output cross-correlations of unlike shape |
| periodic_disturbance | sinusoids at lines of the spectrum of e that v and x do not have |
| time_varying | a gain / lag / residual level that changes from window to window |

The regression tests are partial F-tests (after [1, x]) on the prewhitened residual (an AR
model of e, so that the F distribution holds for a coloured e), at the 99 % level. The line
test compares the Hann periodogram with its running median (Bonferroni over the bins); the
window test compares the largest step / trend statistic of the per-window sequences with
its permutation distribution (windows of a stationary record are exchangeable). Every test
also gives the fraction of the residual energy its signature explains, which ranks the
causes whose test failed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal, stats

from ..identification.correlation import centred_square, cross_correlation
from ..identification.piecewise_linear_ls import interval_index
from ..identification.regression import lagged_columns, solve_least_squares
from ..identification.runs import Runs, several
from .hammerstein import HammersteinModel
from .residual_tests import Evidence
from .split import per_run

LEVEL = 0.99
TREND_BLOCKS = 10  # blocks of the record whose mean levels the drift test compares
PREWHITEN_ORDER = 10
DYNAMIC_POLES = (0.5, 0.8, 0.9, 0.95, 0.98)
FIR_LAGS = 12
MAX_LINES = 6
FRONT_POLES = (0.5, 0.8, 0.95)  # low-pass filters L_p of the input for the input-dynamics signature
FRONT_STEPS = 5
INPUT_MAP_HINGES = 8


@dataclass(frozen=True)
class CauseTest:
    """A cause-specific test: its evidence line and the share of the residual energy its
    signature explains (0..1)."""

    evidence: Evidence
    explained: float

    @property
    def cause(self) -> str:
        return self.evidence.cause

    @property
    def supports(self) -> bool:
        return not self.evidence.passed


# --------------------------------------------------------------------------- regression signatures


def _ar_filter(e: np.ndarray, order: int) -> np.ndarray:
    """[1, c_1..c_p]: the least-squares AR(p) whitening filter of e."""
    rows = np.arange(order, e.size)
    theta = solve_least_squares(lagged_columns(e, range(1, order + 1), rows), e[rows])
    return np.concatenate([[1.0], -theta])


def test_rows(size: int, rows: int | np.ndarray) -> np.ndarray:
    """The samples a test uses: from sample ``rows`` on (an int), or the given indices (the judged
    validation samples of ``coverage``)."""
    return np.arange(rows, size) if isinstance(rows, (int, np.integer)) else np.asarray(rows)


def partial_f_test(e: np.ndarray, nuisance: np.ndarray, columns: np.ndarray,
                   skip: int | np.ndarray) -> tuple[float, float, float]:
    """(F, 99 % critical value, explained share) for e ~ [nuisance, columns] against e ~ nuisance
    on the samples ``test_rows(skip)``.

    F is computed on the AR-prewhitened residual and regressors; the explained share is the
    drop of the residual energy (raw, not whitened) due to ``columns``.
    """
    rows = test_rows(np.size(e), skip)
    e, nuisance, columns = e[rows], nuisance[rows], columns[rows]
    base_fit = nuisance @ solve_least_squares(nuisance, e)
    full = np.column_stack([nuisance, columns])
    raw0 = float(np.sum((e - base_fit) ** 2))
    raw1 = float(np.sum((e - full @ solve_least_squares(full, e)) ** 2))
    order = min(PREWHITEN_ORDER, e.size // 20)
    whiten = _ar_filter(e - base_fit, order) if order > 0 else np.ones(1)
    ew = signal.lfilter(whiten, 1.0, e)[order:]
    fw = signal.lfilter(whiten, 1.0, full, axis=0)[order:]
    nw = fw[:, : nuisance.shape[1]]
    ssr0 = float(np.sum((ew - nw @ solve_least_squares(nw, ew)) ** 2))
    ssr1 = float(np.sum((ew - fw @ solve_least_squares(fw, ew)) ** 2))
    q = int(np.linalg.matrix_rank(fw)) - int(np.linalg.matrix_rank(nw))
    dof = ew.size - fw.shape[1]
    if q <= 0 or dof <= 0 or ssr1 <= 0:
        return 0.0, np.inf, 0.0
    f_value = ((ssr0 - ssr1) / q) / (ssr1 / dof)
    return float(f_value), float(stats.f.ppf(LEVEL, q, dof)), max(0.0, 1.0 - raw1 / raw0) if raw0 > 0 else 0.0


def trend_test(e: np.ndarray, nuisance: np.ndarray, skip: int, blocks: int = TREND_BLOCKS) -> tuple[float, float]:
    """(|t|, 99 % critical value) of the slope of the residual's level along the record: e less
    its least-squares fit on ``nuisance`` is cut into ``blocks`` consecutive blocks, and the
    slope of the block means over the block index is t-tested (blocks - 2 degrees of freedom).
    Block means are nearly independent when the residual's correlation time is shorter than a
    block, which a sample-wise test of a ramp (prewhitened, ``partial_f_test``) cannot rely on:
    whitening a slowly varying residual differences the ramp away."""
    e, nuisance = e[skip:], nuisance[skip:]
    if e.size < 2 * blocks:
        return 0.0, np.inf
    r = e - nuisance @ solve_least_squares(nuisance, e)
    means = np.array([part.mean() for part in np.array_split(r, blocks)])
    fit = stats.linregress(np.arange(blocks), means)
    if not np.isfinite(fit.stderr) or fit.stderr <= 0:
        return 0.0, np.inf
    return abs(float(fit.slope / fit.stderr)), float(stats.t.ppf(1.0 - (1.0 - LEVEL) / 2, blocks - 2))


def hinges(x: np.ndarray, count: int = 5) -> np.ndarray:
    """(x - k_j)_+ at the quantiles j/(count+1) of x."""
    knots = np.quantile(x, np.arange(1, count + 1) / (count + 1))
    return np.maximum(x[:, None] - knots[None, :], 0.0)


def dynamics_basis(s: np.ndarray) -> np.ndarray:
    """Lags 0..FIR_LAGS-1 of s (any dynamics that settles within them, resonances included)
    and its first-order low-pass filters (1 - p)/(1 - p q^-1) at DYNAMIC_POLES (slow modes)."""
    lags = np.column_stack([np.concatenate([np.full(i, s[0]), s[: s.size - i]]) for i in range(FIR_LAGS)])
    smooth = [signal.lfilter([1.0 - p], [1.0, -p], s, zi=[p * s[0]])[0] for p in DYNAMIC_POLES]
    return np.column_stack([lags, *smooth])


def last_direction(v: np.ndarray) -> np.ndarray:
    """sign(v(k) - v(k-1)), held over samples where the input does not move."""
    step = np.sign(np.diff(np.asarray(v, dtype=float), prepend=v[0]))
    index = np.where(step != 0, np.arange(step.size), 0)
    return step[np.maximum.accumulate(index)]


def signature_tests(model: HammersteinModel, v: np.ndarray, x: np.ndarray, e: np.ndarray,
                    skip: int | np.ndarray, runs: Runs | None = None) -> list[CauseTest]:
    """The regression-signature tests on one record (v input, x baseline output, e = y - x), on
    the samples ``test_rows(skip)``; with ``runs`` every filter, lag and difference of the
    regressors starts anew at each run."""
    def through_g(columns: np.ndarray) -> np.ndarray:
        return per_run(lambda c: signal.lfilter(model.b, model.a, c, axis=0), columns, runs)

    def difference(z: np.ndarray) -> np.ndarray:
        return per_run(lambda part: np.diff(part, prepend=part[0]), z, runs)

    fv = model.static(v)
    slope = model.slopes[interval_index(v, model.partition)]
    direction = per_run(last_direction, v, runs)
    nuisance = np.column_stack([np.ones_like(x), x])
    signatures = {
        "output_nonlinearity": ("residual vs static map of simulated output", hinges(x)),
        "output_feedback": ("residual vs G[map of simulated output]", through_g(hinges(x))),
        "parallel_path": ("residual vs linear dynamics of the input", per_run(dynamics_basis, v, runs)),
        "unmodeled_dynamics": ("residual vs linear dynamics of F(input)", per_run(dynamics_basis, fv, runs)),
        "backlash": ("residual vs input direction G[F'(u) sign(du)]",
                     through_g(np.column_stack([slope * direction, direction]))),
    }
    tests = []
    for cause, (name, columns) in signatures.items():
        f_value, critical, explained = partial_f_test(e, nuisance, columns, skip)
        tests.append(CauseTest(Evidence(f"{name} (F)", f_value, critical, f_value <= critical, cause), explained))
    # a loop of its own around the plant (a servo): y = G[f(v - y) - h(y) - phi(dy)] leaves, to first order,
    # G[static maps of the loop error v - x and of the output's difference dx] beyond G[map of x]
    loop = through_g(np.column_stack([hinges(v - x), hinges(difference(x))]))
    f_value, critical, explained = partial_f_test(e, np.column_stack([nuisance, signatures["output_feedback"][1]]),
                                                  loop, skip)
    tests.append(CauseTest(Evidence("residual vs G[maps of the loop error u - x and of dx] beyond G[map of x] (F)",
                                    f_value, critical, f_value <= critical, "output_feedback"), explained))
    # input dynamics y = G2[f(L v)]: f(L v) = f(v + (L - 1) v) ~ f(v) + f'(v) (L - 1) v, so the residual
    # carries G[f'(v) (L_p - 1) v] (slope of the baseline map, and steps at quantiles of v for a map
    # the baseline got wrong) beyond G[static map of v]. The explained share is that of all the static
    # maps of (filtered) inputs: these columns, and the hinges of x (x = G[F(v)] is one filtered input;
    # when G2 is nearly static, y ~ f(L v) is mostly a static map of some filter of the input)
    raw_map = through_g(hinges(v, INPUT_MAP_HINGES))
    knots = np.quantile(v, np.arange(1, FRONT_STEPS + 1) / (FRONT_STEPS + 1))
    weights = np.column_stack([slope, (v[:, None] > knots[None, :]).astype(float)])
    high = [per_run(lambda part, p=p: _low_pass(part, p), v, runs) - v for p in FRONT_POLES]
    front = through_g(np.column_stack([weights * h[:, None] for h in high]))
    f_value, critical, _ = partial_f_test(e, np.column_stack([nuisance, raw_map]), front, skip)
    explained = partial_f_test(e, nuisance, np.column_stack([raw_map, front, hinges(x)]), skip)[2]
    tests.append(CauseTest(Evidence("residual vs G[F'(input) x high-passed input] beyond G[map of input] (F)",
                                    f_value, critical, f_value <= critical, "input_dynamics"), explained))
    return tests


def _low_pass(v: np.ndarray, pole: float) -> np.ndarray:
    """(1 - p) / (1 - p q^-1) v from the steady state at v(0)."""
    return signal.lfilter([1.0 - pole], [1.0, -pole], v, zi=[pole * v[0]])[0]


def correlation_shape_test(v: np.ndarray, y: np.ndarray, max_lag: int = 20,
                           runs: Runs | None = None) -> CauseTest | None:
    """Billings-Fakhouri's separation of a parallel path (paper 003, eqs. 13, 20, 28): for an
    i.i.d. input, a Hammerstein system's first-order cross-correlation phi_x'y'(tau) and its
    second-order one phi_x'^2y'(tau) are both proportional to the same impulse response h(tau);
    a linear path in parallel adds its own impulse response to the first only. The test: the
    2 x (L+1) matrix of the two correlations (tau = 0..L), each row divided by its standard
    error, has rank one up to noise; its smaller singular value squared is ~ chi^2(L) then.
    None when the input is not white (the proportionality needs an i.i.d. input), or (``runs``)
    no run holds the lags."""
    x = np.asarray(v, dtype=float) - np.mean(v)
    n = x.size
    if runs is not None and not np.any(runs.lengths > 2 * max_lag):
        return None
    rho = np.abs(_autocorrelation(x, 10, runs)[1:])
    if np.max(rho) > 4.0 / np.sqrt(n):
        return None
    y = np.asarray(y, dtype=float)
    w = centred_square(v)
    first = cross_correlation(x, y - y.mean(), max_lag, runs)[max_lag:]
    second = cross_correlation(w, y - y.mean(), max_lag, runs)[max_lag:]  # second_order_cross_correlation
    sigma1 = np.sqrt(np.var(x) * np.var(y) / n)
    sigma2 = np.sqrt(np.var(w) * np.var(y) / n)
    smallest = np.linalg.svd(np.vstack([first / sigma1, second / sigma2]), compute_uv=False)[-1]
    value, bound = float(smallest**2), float(stats.chi2.ppf(LEVEL, max_lag))
    ev = Evidence("2nd- vs 1st-order cross-correlation shape (Billings-Fakhouri, chi2)", value, bound, value <= bound,
                  "parallel_path")
    return CauseTest(ev, 0.0)


def _autocorrelation(x: np.ndarray, max_lag: int, runs: Runs | None = None) -> np.ndarray:
    c = cross_correlation(x, x, max_lag, runs)[max_lag:]
    return c / c[0] if c[0] > 0 else c


# --------------------------------------------------------------------------- spectral lines


@dataclass(frozen=True, eq=False)
class LineTest:
    """Lines of the residual spectrum not present in the input's or the simulated output's."""

    frequencies: np.ndarray  # rad/sample, strongest first
    ratio: float  # the strongest line's periodogram / running median
    threshold: float
    explained: float
    periodogram: np.ndarray
    grid: np.ndarray  # rad/sample

    def cause_test(self) -> CauseTest:
        passed = self.frequencies.size == 0
        ev = Evidence("residual spectrum line not in the input's (peak / median)", self.ratio, self.threshold,
                      passed, "periodic_disturbance")
        return CauseTest(ev, 0.0 if passed else self.explained)


def _line_ratio(x: np.ndarray, nfft: int, half_width: int, runs: Runs | None = None) -> np.ndarray:
    """Hann periodogram of x divided by its running median over +-half_width bins. With ``runs``
    Bartlett's average: every run's periodogram (its own mean removed, per unit window energy) on
    the common grid of ``nfft`` bins, averaged over the runs."""
    x = np.asarray(x, dtype=float)
    if runs is None:
        p = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(x.size), nfft)) ** 2
    else:
        p = np.mean([np.abs(np.fft.rfft((part - part.mean()) * np.hanning(part.size), nfft)) ** 2
                     / max(float(np.sum(np.hanning(part.size) ** 2)), 1e-300) for part in runs.split(x)], axis=0)
    med = ndimage.median_filter(p, size=2 * half_width + 1, mode="nearest")
    return p / np.maximum(med, 1e-300 + 1e-12 * float(np.max(p)))


def _line_threshold(n: int, level: float, averaged: int) -> float:
    """The Bonferroni level over the ~n/2 bins of the periodogram / median ratio: for Gaussian
    noise a periodogram is Exp(1)-distributed (its median ln 2), an average of ``averaged`` ones
    Gamma(averaged, 1/averaged)."""
    if averaged == 1:
        return float(np.log(0.5 * n / (1.0 - level)) / np.log(2.0))
    gamma = stats.gamma(averaged, scale=1.0 / averaged)
    return float(gamma.isf((1.0 - level) / (0.5 * n)) / gamma.median())


def run_indicators(runs: Runs) -> np.ndarray:
    """Column r is 1 on the samples of run r, 0 elsewhere (a constant per run)."""
    label = np.repeat(np.arange(runs.count), runs.lengths)
    return (label[:, None] == np.arange(runs.count)[None, :]).astype(float)


def run_waves(frequencies: np.ndarray, runs: Runs) -> np.ndarray:
    """Columns cos(w k), sin(w k) for every frequency w, k the sample within its run, a pair per
    run (zero outside it): a sinusoid with every run's own phase and amplitude. Order: frequency,
    run, cos/sin."""
    local = np.arange(runs.total) - np.repeat(np.asarray(runs.starts, dtype=int), runs.lengths)
    inside = run_indicators(runs)
    return np.column_stack([f(w * local) * inside[:, r] for w in frequencies for r in range(runs.count)
                            for f in (np.cos, np.sin)] or [np.zeros((runs.total, 0))])


def spectral_lines(e: np.ndarray, references: list[np.ndarray], level: float = LEVEL,
                   runs: Runs | None = None) -> LineTest:
    """Peaks of the residual periodogram above the Bonferroni level of its running median
    (for Gaussian noise, periodogram / median ~ Exp(1) / ln 2 in each of the ~N/2 bins), at
    frequencies where no reference signal (input, simulated output) has a line. With several
    ``runs`` (of e and the references) the periodograms are Bartlett's average of the runs' own
    (``_line_ratio``: a disturbance keeps its frequency but has its own phase in every run; the
    grid that of the longest run) and the share explained is that of sinusoids with a phase per run."""
    runs = several(runs)
    n = e.size if runs is None else int(runs.lengths.max())
    pad = 4
    nfft = pad * int(2 ** np.ceil(np.log2(n)))
    bins_per_natural = nfft / n
    half = int(32 * bins_per_natural)
    ratio = _line_ratio(e, nfft, half, runs)
    threshold = _line_threshold(n, level, 1 if runs is None else runs.count)
    grid = 2 * np.pi * np.arange(ratio.size) / nfft
    lobe = int(np.ceil(3 * bins_per_natural))
    reference_lines = np.concatenate([_peaks(_line_ratio(r, nfft, half, runs), threshold, lobe) for r in references])
    candidates = _peaks(ratio, threshold, lobe)
    # a reference line within one DFT bin (2 pi / N) is the same line
    distinct = [f for f in candidates if not np.any(np.abs(reference_lines - f) < 2 * np.pi / n)]
    frequencies = np.array(sorted(distinct, key=lambda f: -ratio[int(round(f * nfft / (2 * np.pi)))])[:MAX_LINES])
    peaks = np.array([int(round(f * nfft / (2 * np.pi))) for f in frequencies], dtype=int)
    explained = 0.0
    if frequencies.size:
        if runs is None:
            k = np.arange(n)
            basis = np.column_stack([np.ones(n)] + [f(w * k) for w in frequencies for f in (np.cos, np.sin)])
        else:
            basis = np.column_stack([run_indicators(runs), run_waves(frequencies, runs)])
        fit = basis @ solve_least_squares(basis, e)
        e0 = e - e.mean() if runs is None else e - basis[:, : runs.count] @ solve_least_squares(
            basis[:, : runs.count], e)
        explained = max(0.0, 1.0 - float(np.sum((e - fit) ** 2)) / float(np.sum(e0**2)))
    strongest = float(ratio[peaks[0]]) if peaks.size else float(np.max(ratio[3 * lobe :]))
    return LineTest(frequencies, strongest, threshold, explained, ratio, grid)


def _peaks(ratio: np.ndarray, threshold: float, lobe: int) -> np.ndarray:
    """Frequencies (rad/sample, interpolated) of the local maxima of a periodogram ratio above
    ``threshold``, away from 0 (3 main-lobe widths)."""
    nfft = 2 * (ratio.size - 1)
    peaks = signal.argrelmax(ratio, order=lobe)[0]
    peaks = peaks[(ratio[peaks] > threshold) & (peaks > 3 * lobe)]
    return np.array([_refine_peak(ratio, p) * 2 * np.pi / nfft for p in peaks])


def _refine_peak(p: np.ndarray, i: int) -> float:
    """Fractional bin of a peak by parabolic interpolation of the log periodogram."""
    if i <= 0 or i >= p.size - 1:
        return float(i)
    a, b, c = np.log(p[i - 1 : i + 2])
    denom = a - 2 * b + c
    return float(i + 0.5 * (a - c) / denom) if denom < 0 else float(i)


# --------------------------------------------------------------------------- windows over time


@dataclass(frozen=True, eq=False)
class WindowTest:
    """Per-window gain, lag and residual level of the baseline over the whole record."""

    starts: np.ndarray  # first sample of each window (in the concatenated record)
    gain: np.ndarray
    statistic: float
    threshold: float
    change_point: int | None  # sample where the best step sits (when a step beats a trend)
    drift_per_sample: float | None  # relative gain change per sample (when a trend wins)
    explained: float

    def cause_test(self) -> CauseTest:
        passed = self.statistic <= self.threshold
        ev = Evidence("change of gain/lag/residual level across windows (max t, permutation)",
                      self.statistic, self.threshold, passed, "time_varying")
        return CauseTest(ev, 0.0 if passed else self.explained)


def _step_trend(seq: np.ndarray) -> tuple[float, float, int]:
    """(largest |t| of a mean step, |t| of a linear trend, index of the best step) of the
    per-window sequences (rows = windows, columns = sequences; maxima over the columns)."""
    m = seq.shape[0]
    idx = np.arange(m) - (m - 1) / 2
    centred = seq - seq.mean(axis=0)
    slope = idx @ centred / (idx @ idx)
    res = centred - np.outer(idx, slope)
    se = np.sqrt(np.sum(res**2, axis=0) / max(m - 2, 1) / (idx @ idx)) + 1e-300
    trend = float(np.max(np.abs(slope) / se))
    j = np.arange(2, m - 1)[:, None]  # a step after the first j windows
    head_sum = np.cumsum(centred, axis=0)[j[:, 0] - 1]
    total_sq = np.sum(centred**2, axis=0)
    mean1, mean2 = head_sum / j, -head_sum / (m - j)
    resid = total_sq - j * mean1**2 - (m - j) * mean2**2
    sp = np.sqrt(np.maximum(resid, 1e-300) / (m - 2))
    t = np.max(np.abs(mean1 - mean2) / (sp * np.sqrt(1.0 / j + 1.0 / (m - j))), axis=1)
    best = int(np.argmax(t))
    return float(t[best]), trend, int(j[best, 0])


def windowed_variation(y: np.ndarray, x: np.ndarray, skip: int, permutations: int = 400,
                       runs: Runs | None = None) -> WindowTest:
    """Split the record (after ``skip`` transient samples) in windows; in each, fit
    y ~ c + g x + l dx (gain g, lag l) and take the residual level; test the three sequences
    for a step or a trend against their permutation distribution (fixed seed). With ``runs``
    the windows that straddle two runs are left out (and dx starts anew at every run)."""
    dx = per_run(lambda part: np.diff(part, prepend=part[0]), np.asarray(x, float), runs)[skip:]
    dx[:1] = 0.0  # the record starts at the first sample after the transient
    y, x = np.asarray(y, float)[skip:], np.asarray(x, float)[skip:]
    windows = int(np.clip(y.size // 120, 16, 40))  # >= 16: a perfect step is then a 1e-4 event, not 3 %
    length = y.size // windows
    starts = skip + length * np.arange(windows)
    if runs is not None and runs.count > 1:
        label = np.repeat(np.arange(runs.count), runs.lengths)
        starts = starts[label[starts] == label[starts + length - 1]]
        windows = starts.size
        if windows < 4:
            return WindowTest(starts, np.zeros(windows), 0.0, np.inf, None, None, 0.0)
    rows, ssr_local = [], 0.0
    for w in range(windows):
        s = slice(starts[w] - skip, starts[w] - skip + length)
        basis = np.column_stack([np.ones(length), x[s], dx[s]])
        theta = solve_least_squares(basis, y[s])
        r = y[s] - basis @ theta
        ssr_local += float(np.sum(r**2))
        rows.append([theta[1], theta[2], np.log(np.sqrt(np.mean(r**2)) + 1e-300)])
    seq = np.asarray(rows)
    step, trend, j = _step_trend(seq)
    observed = max(step, trend)
    rng = np.random.default_rng(0)
    null = [max(_step_trend(seq[rng.permutation(windows)])[:2]) for _ in range(permutations)]
    threshold = float(np.quantile(null, LEVEL))
    used = np.concatenate([np.arange(k - skip, k - skip + length) for k in starts])
    basis = np.column_stack([np.ones(used.size), x[used], dx[used]])
    ssr_global = float(np.sum((y[used] - basis @ solve_least_squares(basis, y[used])) ** 2))
    extra_parameters = 3.0 * (windows - 1) / (windows * length)
    explained = max(0.0, 1.0 - ssr_local / ssr_global - extra_parameters) if ssr_global > 0 else 0.0
    gain = seq[:, 0]
    change_point = drift = None
    if step >= trend:
        change_point = int(starts[j])
    else:
        idx = np.arange(windows)
        drift = float(np.polyfit(idx, gain, 1)[0] / length / max(abs(np.mean(gain)), 1e-12))
    return WindowTest(starts, gain, observed, threshold, change_point, drift, explained)
