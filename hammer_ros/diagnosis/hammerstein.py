"""The baseline: a Hammerstein model with a piecewise-linear map, fitted by PLLS (paper 001)
and refined on the simulation error.

Why this model: the piecewise-linear map in point-slope form (paper 001, eqs. 5-11) holds
the input nonlinearities a plant actually has (saturation, dead zone, asymmetric gains,
relays) as well as smooth ones, where a low-degree polynomial (paper 000, 003) cannot; PLLS
gives it in one least-squares solve without assumptions on the input distribution (CLS and
Billings-Fakhouri need a Gaussian or separable input); and the simulation-error refinement
(``simulation_error``) removes the equation-error bias that output noise causes, so the
baseline is the best free-run Hammerstein simulator of this structure, the quantity the
diagnosis compares. The breakpoints sit at quantiles of the estimation input, so every
interval holds data.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import linalg, signal, stats

from ..errors import IdentificationError
from ..identification.linear import LinearModel
from ..identification.piecewise_linear_ls import (
    drop_empty_intervals,
    plls,
    point_slope_basis,
    point_slope_map,
    rank_one_factors,
)
from ..identification.regression import build_regression, lagged_columns, solve_least_squares
from ..identification.result import rms_error
from ..identification.runs import Runs
from ..identification.simulation_error import refine, settling_samples, stabilised_denominator, steady_state_filter
from ..identification.static_maps import PiecewiseLinearMap
from .split import held_back, per_run, runs_tail

MAX_ORDER_SEARCH = 4


@dataclass(frozen=True, eq=False)
class HammersteinModel:
    """y = B(q^-1)/A(q^-1) [F(v)] with F(v) = eta(v)^T mu + kappa (paper 001, eq. 8) on the
    partition c with primary index r; a = [1, a_1..a_n], b = [b_0..b_n] (b_i = 0 below the
    relative degree)."""

    a: np.ndarray
    b: np.ndarray
    partition: np.ndarray
    primary: int
    slopes: np.ndarray
    kappa: float

    @property
    def order(self) -> int:
        return self.a.size - 1

    @property
    def delay(self) -> int:
        return self.linear.delay

    @property
    def linear(self) -> LinearModel:
        return LinearModel(self.b, self.a)

    @property
    def nonlinearity(self) -> PiecewiseLinearMap:
        return point_slope_map(self.partition, self.primary, self.slopes, self.kappa)

    def basis(self, v: np.ndarray) -> np.ndarray:
        return point_slope_basis(v, self.partition, self.primary)

    def static(self, v: np.ndarray) -> np.ndarray:
        """F(v)."""
        return self.basis(v) @ self.slopes + self.kappa

    def simulate(self, v: np.ndarray) -> np.ndarray:
        """Free-run output from the steady state at v(0)."""
        return steady_state_filter(self.b, self.a, self.static(v))

    def parameter_count(self) -> int:
        return self.order + np.count_nonzero(self.b) + self.slopes.size

    def simulate_runs(self, v: np.ndarray, runs: Runs | None) -> np.ndarray:
        """``simulate`` started anew at every run (at rest at the run's first input)."""
        return per_run(self.simulate, v, runs)


class HammersteinParameters:
    """theta = [a_1..a_n, b_d..b_n without the largest one, mu, kappa (, c)]: the model's free
    parameters for the simulation-error refinement; the largest numerator coefficient stays
    fixed because the scale of G and F is not identifiable (paper 001, eq. 3). With
    ``free_knots`` the breakpoints c are free too (kept sorted)."""

    def __init__(self, model: HammersteinModel, free_knots: bool = False):
        self.template = model
        self.free_knots = free_knots
        d = model.delay
        self.free_b = np.arange(d, model.b.size)
        self.fixed = d + int(np.argmax(np.abs(model.b[d:])))
        self.free_b = self.free_b[self.free_b != self.fixed]
        self.size = model.order + self.free_b.size + model.slopes.size + 1 + (model.partition.size if free_knots else 0)

    def pack(self, model: HammersteinModel) -> np.ndarray:
        knots = model.partition if self.free_knots else []
        return np.concatenate([model.a[1:], model.b[self.free_b], model.slopes, [model.kappa], knots])

    def unpack(self, theta: np.ndarray) -> HammersteinModel:
        n, nb, ns = self.template.order, self.free_b.size, self.template.slopes.size
        b = self.template.b.copy()
        b[self.free_b] = theta[n : n + nb]
        rest = theta[n + nb + ns + 1 :]
        partition = np.sort(rest) if self.free_knots else self.template.partition
        return replace(self.template, a=np.concatenate([[1.0], theta[:n]]), b=b, partition=partition,
                       slopes=np.asarray(theta[n + nb : n + nb + ns]), kappa=float(theta[n + nb + ns]))


def quantile_partition(v: np.ndarray, count: int, tails: bool = False) -> np.ndarray:
    """``count`` breakpoints at the quantiles i/(count+1) of v (``tails``: plus the 1 % and
    99 % quantiles, for maps that keep bending beyond the bulk of the data, e.g. polynomials),
    without duplicates and without those that would leave an interval of paper 001's eq. 6
    empty."""
    probabilities = np.arange(1, count + 1) / (count + 1)
    if tails:
        probabilities = np.concatenate([[0.01], probabilities, [0.99]])
    knots = np.unique(np.quantile(np.asarray(v, dtype=float), probabilities))
    return drop_empty_intervals(v, knots)


def default_breakpoints(samples: int) -> int:
    """3 breakpoints for short records, up to 8 from 2400 samples on (about 300 per interval)."""
    return int(np.clip(samples // 300, 3, 8))


def plls_hammerstein(v: np.ndarray, y: np.ndarray, order: int, delay: int, partition: np.ndarray) -> HammersteinModel:
    """PLLS of paper 001 sec. 4.1 (equation error), with a stabilised denominator."""
    est = plls(v, y, order, delay, "hammerstein", partition=partition)
    f, primary = est.nonlinearity, est.primary_index
    return HammersteinModel(stabilised_denominator(est.linear.a), est.linear.b, partition, primary,
                            f.slopes, float(f.values[primary - 1]))


def steiglitz_mcbride(model: HammersteinModel, v: np.ndarray, y: np.ndarray, iterations: int = 4,
                      runs: Runs | None = None) -> HammersteinModel:
    """PLLS on data prefiltered by 1/A_hat, repeated (Steiglitz & McBride 1965): each pass
    solves the PLLS regression of paper 001 (eq. 23: y/A_hat on eta(v)/A_hat and the
    prefiltered constant) and factors it by rank one (eqs. 35-38). At convergence the equation
    error is the simulation error, so the estimate loses the equation-error bias that output
    noise causes: a better start for the refinement than PLLS alone, in the cases where it is
    (``fit_hammerstein`` keeps the better of the two). With ``runs`` every run is filtered on its
    own and no regressor reaches into another run."""
    eta = model.basis(v)
    skip = transient_samples(model.linear.poles, v.size)
    a = model.a
    current = model
    for _ in range(iterations):
        def prefiltered(x: np.ndarray, a: np.ndarray = a) -> np.ndarray:
            return per_run(lambda part: signal.lfilter([1.0], a, part, axis=0), x, runs)

        reg = build_regression(prefiltered(y), prefiltered(eta), model.order, model.delay, runs=runs)
        constant = prefiltered(np.ones(v.size))[reg.rows]
        theta = solve_least_squares(np.column_stack([reg.phi, constant])[skip:], reg.target[skip:])
        a_new, coefficients = reg.split(theta[:-1])
        b, mu = rank_one_factors(coefficients, None, a_new)
        if not np.all(np.isfinite(b)) or abs(np.sum(b)) < 1e-12:
            return current
        a = stabilised_denominator(np.concatenate([[1.0], a_new]))
        current = replace(model, a=a, b=np.concatenate([np.zeros(model.delay), b]), slopes=mu,
                          kappa=float(theta[-1] / np.sum(b)))
    return current


def transient_samples(model_poles: np.ndarray, samples: int) -> int:
    """Samples left out of a fit's cost at the start of a record (the unknown initial state
    decays in them): the settling time of the slowest pole, at most a fifth of the record."""
    return settling_samples(model_poles, cap=max(samples // 5, 1))


def refine_hammerstein(model: HammersteinModel, v: np.ndarray, y: np.ndarray, iterations: int = 30,
                       free_knots: bool = False, runs: Runs | None = None) -> HammersteinModel:
    """The model minimising the simulation error on (v, y), started from ``model`` (``runs``:
    every run simulated from rest at its first input)."""
    params = HammersteinParameters(model, free_knots)
    eta = model.basis(v)

    def simulate(theta: np.ndarray) -> np.ndarray:
        m = params.unpack(theta)
        basis = m.basis(v) if free_knots else eta
        return per_run(lambda x: steady_state_filter(m.b, m.a, x), basis @ m.slopes + m.kappa, runs)

    skip = transient_samples(model.linear.poles, y.size)
    refined = params.unpack(refine(simulate, params.pack(model), y, iterations, skip))
    if not refined.linear.is_stable():
        refined = replace(refined, a=stabilised_denominator(refined.a))
    return refined


FREE_KNOT_SAMPLES = 20000  # the breakpoints are refined on at most this many (the last) samples
SELECTION_SAMPLES = 20000  # order, delay and breakpoints are chosen on at most this many


def fit_hammerstein(v: np.ndarray, y: np.ndarray, order: int, delay: int,
                    partition: np.ndarray | None = None, free_knots: bool = True,
                    denominators: tuple[np.ndarray, ...] = (), runs: Runs | None = None) -> HammersteinModel:
    """PLLS estimate on a quantile partition (or its Steiglitz-McBride iteration, or that
    iteration started from one of the given ``denominators``, whichever simulates best),
    refined on the simulation error with the breakpoints fixed, then (``free_knots``) with the
    breakpoints free as well (``free_breakpoints``). With ``runs`` no simulation or regressor
    crosses a run's boundary (the PLLS start's regression aside: only a start)."""
    if partition is None:
        partition = quantile_partition(v, default_breakpoints(v.size))
    start = plls_hammerstein(v, y, order, delay, partition)
    skip = transient_samples(start.linear.poles, v.size)
    candidates = [start, steiglitz_mcbride(start, v, y, runs=runs)]
    candidates += [steiglitz_mcbride(replace(start, a=a), v, y, 3, runs) for a in denominators]
    costs = [float(np.sum((y - m.simulate_runs(v, runs))[skip:] ** 2)) for m in candidates]
    model = refine_hammerstein(candidates[int(np.nanargmin(costs))], v, y, runs=runs)
    return free_breakpoints(model, v, y, runs) if free_knots else model


def free_breakpoints(model: HammersteinModel, v: np.ndarray, y: np.ndarray,
                     runs: Runs | None = None) -> HammersteinModel:
    """The refinement with the breakpoints free as well, so that a kink, a dead zone or a relay
    jump is not smeared over the gap between two quantiles (on the last FREE_KNOT_SAMPLES
    samples, then the other parameters on all of them)."""
    tail, tail_runs = runs_tail(runs, v.size, FREE_KNOT_SAMPLES)
    model = prune_breakpoints(refine_hammerstein(model, v[tail], y[tail], iterations=15, free_knots=True,
                                                 runs=tail_runs), v)
    return refine_hammerstein(model, v, y, iterations=10, runs=runs) if tail.start else model


def prune_breakpoints(model: HammersteinModel, v: np.ndarray) -> HammersteinModel:
    """The same map on the data without the breakpoints that leave an interval empty (free
    breakpoints can wander out of the data or onto each other): slopes and offset re-fitted to
    the map's values on v, which they reproduce exactly between the kept breakpoints. When none
    is left (a two-valued input, e.g. a PRBS, whose one breakpoint wandered past a level), one
    breakpoint midway between the input's extremes holds the map."""
    try:
        kept = drop_empty_intervals(v, model.partition)
    except IdentificationError:
        kept = drop_empty_intervals(v, np.array([0.5 * (float(np.min(v)) + float(np.max(v)))]))
    if np.array_equal(kept, model.partition):
        return model
    primary = max(1, kept.size // 2)
    basis = np.column_stack([point_slope_basis(v, kept, primary), np.ones(v.size)])
    theta = solve_least_squares(basis, model.static(v))
    return replace(model, partition=kept, primary=primary, slopes=theta[:-1], kappa=float(theta[-1]))


def bic(y: np.ndarray, y_sim: np.ndarray, parameters: int) -> float:
    """Bayesian information criterion N ln(mean squared error) + k ln N."""
    n = y.size
    mse = float(np.mean((y - y_sim) ** 2))
    return n * np.log(max(mse, 1e-300)) + parameters * np.log(n)


def equation_error_bic(model: HammersteinModel, v: np.ndarray, y: np.ndarray, runs: Runs | None = None) -> float:
    """BIC of the one-step equation error A(q) y - B(q) F(v) (for the choice of the delay; with
    ``runs`` from the order-th sample of every run)."""
    runs = Runs.one(y.size) if runs is None else runs
    pairs = np.column_stack([y, model.static(v)])
    e = runs.simulate(lambda p: np.convolve(p[:, 0], model.a)[: p.shape[0]] - np.convolve(p[:, 1], model.b)[
        : p.shape[0]], pairs)[runs.rows(model.order)]
    return bic(np.zeros(e.size), e, model.parameter_count())


def select_delay(v: np.ndarray, y: np.ndarray, order: int, partition: np.ndarray, runs: Runs | None = None) -> int:
    """Relative degree 1..min(3, order) with the smallest equation-error BIC (a sampled plant
    driven through a zero-order hold has no direct feedthrough; pass delay 0 explicitly)."""
    scores = {}
    for d in range(1, min(3, order) + 1):
        try:
            scores[d] = equation_error_bic(plls_hammerstein(v, y, order, d, partition), v, y, runs)
        except (IdentificationError, np.linalg.LinAlgError, ValueError):
            continue
    if not scores:
        raise IdentificationError("no Hammerstein model could be fitted to the estimation data")
    return min(scores, key=scores.get)


MAX_DEAD_TIME = 12  # samples of pure input delay searched ahead of the linear block
DEAD_TIME_GAIN = 0.5  # within the order, a shift must halve the simulation RMS


def input_delay(v: np.ndarray, y: np.ndarray, order: int, runs: Runs | None = None) -> int | None:
    """The total input delay D: the first lag l = 0..MAX_DEAD_TIME + 1 whose input coefficients
    are significant in an over-parameterised ARX model y(k) = -sum_j a_j y(k-j) +
    sum_l eta(v(k-l))^T g_l + c (order + 2 poles; eta the point-slope basis of paper 001 eq. 9
    on 3 quantile breakpoints, so that any input map shows up): a partial F-test per lag at
    0.1 % over all lags (Bonferroni). None when no lag is significant."""
    n = order + 2
    lags = MAX_DEAD_TIME + 2
    partition = quantile_partition(v, 3)
    basis = point_slope_basis(v, partition, max(1, partition.size // 2))
    q = basis.shape[1]
    rows = (Runs.one(v.size) if runs is None else runs).rows(max(n, lags - 1))
    phi = np.hstack([-lagged_columns(y, range(1, n + 1), rows), lagged_columns(basis, range(lags), rows),
                     np.ones((rows.size, 1))])
    dof = rows.size - phi.shape[1]
    if dof < 10:
        return None
    q_factor, r = np.linalg.qr(phi)
    if np.min(np.abs(np.diag(r))) < 1e-10 * np.max(np.abs(np.diag(r))):
        return None
    r_inv = linalg.solve_triangular(r, np.eye(r.shape[0]))
    theta = r_inv @ (q_factor.T @ y[rows])  # least squares by the same QR
    sigma2 = float(np.sum((y[rows] - phi @ theta) ** 2)) / dof
    critical = stats.f.isf(1e-3 / lags, q, dof)
    for lag in range(lags):
        block = slice(n + lag * q, n + (lag + 1) * q)
        g = theta[block]
        covariance = r_inv[block] @ r_inv[block].T  # the (Phi'Phi)^-1 block of lag l
        if g @ np.linalg.solve(covariance, g) / q / sigma2 > critical:
            return lag
    return None


def select_dead_time(v: np.ndarray, y: np.ndarray, order: int | None, runs: Runs | None = None) -> int:
    """Dead time s: samples of pure delay of the input ahead of the linear block, moved into the
    data (v(k - s)) so that the model of the nominal order n holds it.

    With the total delay D of ``input_delay``: s = 0 when D <= 1 or unclear; s = D - 1 when
    D > n, a relative degree the order cannot hold (bus latency, a low-order plant with dead
    time), which would otherwise be read as missing dynamics. For 2 <= D <= n both readings
    are fitted on the simulation error (``fit_hammerstein``, breakpoints fixed): relative
    degree D (n - D + 1 numerator coefficients) and the shift D - 1 with relative degree 1
    (n of them: a plant with zeros as well as the delay); the shift is kept only when it
    cuts the simulation RMS to DEAD_TIME_GAIN of the other or less. (The equation error
    alone, or a 10 % margin, prefers a shift on short noisy records too often: measured on
    the generated cases, it cost more than it mended.)"""
    n = order or MAX_ORDER_SEARCH
    tail, runs = runs_tail(runs, np.size(v), SELECTION_SAMPLES)  # chosen on the last samples, like the order
    v, y = np.asarray(v, dtype=float)[tail], np.asarray(y, dtype=float)[tail]
    total = input_delay(v, y, n, runs)
    if total is None or total <= 1:
        return 0
    if total > n:
        return total - 1
    partition = quantile_partition(v, default_breakpoints(v.size))
    errors = {}
    for shift, d in ((0, total), (total - 1, 1)):
        shifted = per_run(lambda part, shift=shift: held_back(part, shift), v, runs)
        try:
            model = fit_hammerstein(shifted, y, n, d, partition, free_knots=False, runs=runs)
        except (IdentificationError, np.linalg.LinAlgError, ValueError):
            return 0
        skip = max(transient_samples(model.linear.poles, v.size), total + n)
        errors[shift] = rms_error(y[skip:], model.simulate_runs(shifted, runs)[skip:])
    return total - 1 if errors[total - 1] <= DEAD_TIME_GAIN * errors[0] else 0


def fit_baseline(v: np.ndarray, y: np.ndarray, order: int | None, delay: int | None,
                 runs: Runs | None = None) -> HammersteinModel:
    """The baseline: the nominal order when given (else the order 1..4 with the smallest
    simulation-error BIC), the given delay (else the one with the smallest equation-error BIC),
    the breakpoints among ``breakpoint_counts`` with the smallest simulation-error BIC, then
    the breakpoints refined (``free_breakpoints``). The choices are made on the last
    SELECTION_SAMPLES samples; the chosen model is then refined on all of them. ``runs``: every
    simulation starts anew at each run (at rest at its first input), no regressor crosses a run."""
    tail, tail_runs = runs_tail(runs, np.size(v), SELECTION_SAMPLES)
    chosen = _select_baseline(v[tail], y[tail], order, delay, tail_runs)
    if tail.start:
        chosen = refine_hammerstein(chosen, v, y, iterations=15, runs=runs)
    return free_breakpoints(chosen, v, y, runs)


def _select_baseline(v: np.ndarray, y: np.ndarray, order: int | None, delay: int | None,
                     runs: Runs | None) -> HammersteinModel:
    partition = quantile_partition(v, default_breakpoints(v.size))
    if order:
        best_order = order
        best_delay = select_delay(v, y, order, partition, runs) if delay is None else min(delay, order)
    else:
        scored = []
        for n in range(1, MAX_ORDER_SEARCH + 1):
            d = select_delay(v, y, n, partition, runs) if delay is None else min(delay, n)
            scored.append((_bic(fit_hammerstein(v, y, n, d, partition, free_knots=False, runs=runs), v, y, runs),
                           n, d))
        _, best_order, best_delay = min(scored)
    fits = []
    for count, tails in breakpoint_counts(v.size):
        try:
            partition = quantile_partition(v, count, tails)
            model = fit_hammerstein(v, y, best_order, best_delay, partition, free_knots=False, runs=runs)
        except IdentificationError:
            continue
        fits.append((_bic(model, v, y, runs), count, model))
    if not fits:
        raise IdentificationError("no Hammerstein model could be fitted to the estimation data")
    return min(fits, key=lambda f: f[0])[2]


def breakpoint_counts(samples: int) -> tuple[tuple[int, bool], ...]:
    """(number of quantile breakpoints, with tail breakpoints) tried by the baseline: 3 .. 16
    breakpoints, at least ~150 samples per interval."""
    counts = [c for c in (3, 6, 10, 16) if c == 3 or samples >= 150 * (c + 1)]
    return tuple((c, tails) for c in counts for tails in ((False, True) if c >= 10 else (False,)))


def _bic(model: HammersteinModel, v: np.ndarray, y: np.ndarray, runs: Runs | None = None) -> float:
    skip = transient_samples(model.linear.poles, v.size)
    return bic(y[skip:], model.simulate_runs(v, runs)[skip:], model.parameter_count())
