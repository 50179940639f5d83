"""Piecewise-linear least squares (PLLS): Van Pelt & Bernstein, paper 001.

Three model structures (paper 001, Fig. 1 and eq. 2), with G(q^-1) = B(q^-1) / A(q^-1)
strictly proper (eq. 1):

- ``hammerstein``            y = G [f(u)]            (sec. 4.1, eqs. 12-38)
- ``feedback``               y = G [u - h(y)]        (sec. 4.2, eqs. 39-62, Proposition 1)
- ``hammerstein_feedback``   y = G [f(u) - h(y)]     (sec. 4.3, eqs. 63-71)

f and h are continuous piecewise-linear maps in the point-slope form of eqs. 5-11: a
partition c_1 < ... < c_p, the slopes mu_1..mu_{p+1} on (-inf, c_1], (c_1, c_2], ..., (c_p, inf)
and the value kappa = f(c_r) at the primary breakpoint c_r, so that f(u) = mu^T eta(u) + kappa
(eq. 8). h is the same with (y, d, q, s, nu, lambda, zeta) for (u, c, p, r, mu, kappa, eta).

Each structure is linear in a lifted parameter vector theta~ (eqs. 26, 49, 68), estimated by
least squares on the shared regression builder (``build_regression`` with eta(u) as the
multi-channel input; for the feedback structures the output columns y(k-j) are replaced by
zeta(y(k-j)), since 1^T zeta(y) = y - d_s, eq. 41). The blocks are then recovered by a rank-1
approximation (eqs. 35-37) and by Proposition 1 (eqs. 60-62).

The representation is not unique (sec. 2, eq. 3); three free parameters fix it:

- ``beta`` (input gain, eq. 37): b = v_1 / beta, mu = beta sigma_1 u_1. Default None: the
  linear block gets unit static gain, G(1) = B(1)/A(1) = 1, so f(u) is the steady-state output
  for a constant input u (the normalisation paper 000 uses for its G); where G has no finite,
  non-zero static gain (|B(1)| or |A(1)| < 1e-9 ||.||, e.g. an integrator) b gets unit norm.
  A number is used as in eq. 37, with the sign of the singular vectors fixed by 1^T v_1 >= 0.
- ``alpha`` (stability, eqs. 60-61): moves a linear feedback alpha y between h and A,
  h -> h - alpha y, A -> A + alpha B. Default 0: a = row mean of vec^-1(theta_A), i.e. the
  slopes of h sum to zero over its q+1 intervals.
- ``gamma`` (offset, eq. 71): lambda = h(d_s) = gamma (Hammerstein/feedback only; in the
  feedback structure lambda comes from eq. 62). Default 0.

The identified model's input-output behaviour does not depend on (beta, alpha, gamma); the
paper (sec. 5) and our tests fix them to compare the blocks with the simulated system.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import IdentificationError, UsageError
from .compiled_loops import numba_enabled
from .instrumental import check_reference, reference_part, solve_instrumental
from .linear import LinearModel
from .methods import IdentifyOptions
from .regression import Regression, build_regression, lagged_columns, solve_least_squares
from .result import IdentificationResult
from .runs import Runs, per_run, several
from .simulate import simulate_feedback, simulate_hammerstein, simulate_hammerstein_feedback
from .static_maps import PiecewiseLinearMap, map_parameters
from .uncertainty import Uncertainty, guarded, propagate, regression_covariance

STRUCTURES = ("hammerstein", "feedback", "hammerstein_feedback")
DEFAULT_BREAKPOINTS = 10  # p = 10 as in paper 001, eq. 74
INSTRUMENT_PASSES = 2  # instrumental-variable passes after least squares (``plls(instrumental=True)``)


# --------------------------------------------------------------------------- point-slope basis


def interval_index(x: np.ndarray, partition: np.ndarray) -> np.ndarray:
    """delta(x) - 1 of eq. 6 (0-based): 0 for x <= c_1, i for c_i < x <= c_{i+1}, p for x > c_p."""
    return np.searchsorted(np.asarray(partition, dtype=float), np.asarray(x, dtype=float), side="left")


def point_slope_basis(x: np.ndarray, partition: np.ndarray, primary: int) -> np.ndarray:
    """eta(x) of eqs. 9-11 for every sample: an N x (p+1) matrix with f(x) = eta(x) mu + kappa.

    ``primary`` is the 1-based primary index r (kappa = f(c_r)). Eqs. 10-11 say that eta_i(x)
    is the signed length of the part of the path from c_r to x that lies in interval i
    ([c_{i-1}, c_i], with c_0 = -inf, c_{p+1} = +inf), i.e.

        eta_i(x) = clip(x, c_{i-1}, c_i) - clip(c_r, c_{i-1}, c_i),

    which gives u - c_delta, the full (negative) lengths c_{j-1} - c_j between delta and r
    for delta <= r (eq. 10), and u - c_{delta-1} after the full lengths c_j - c_{j-1} for
    delta > r (eq. 11). The output basis zeta(y) (sec. 4.2) is the same function of y.
    Sum over i: x - c_r (eq. 41).
    """
    c = np.asarray(partition, dtype=float)
    if not 1 <= primary <= c.size:
        raise ValueError(f"primary index must be in 1..{c.size} (got {primary})")
    lower = np.concatenate([[-np.inf], c])
    upper = np.concatenate([c, [np.inf]])
    x = np.asarray(x, dtype=float)[:, None]
    return np.clip(x, lower, upper) - np.clip(c[primary - 1], lower, upper)


def point_slope_map(partition: np.ndarray, primary: int, slopes: np.ndarray, value: float) -> PiecewiseLinearMap:
    """The map f(x) = mu^T eta(x) + kappa (eq. 8) as knots (c_i, f(c_i)) and the outer slopes."""
    c = np.asarray(partition, dtype=float)
    slopes = np.asarray(slopes, dtype=float)
    values = point_slope_basis(c, c, primary) @ slopes + value
    return PiecewiseLinearMap(c, values, float(slopes[0]), float(slopes[-1]))


def _interval_text(partition: np.ndarray, i: int) -> str:
    lo = "-inf" if i == 0 else f"{partition[i - 1]:g}"
    hi = "inf)" if i == partition.size else f"{partition[i]:g}]"
    return f"({lo}, {hi}"


def check_partition(x: np.ndarray, partition: np.ndarray, signal: str) -> None:
    """Raise IdentificationError naming the first interval (eq. 6) that holds no sample of x:
    Phi^T Phi is then singular (paper 001, end of sec. 5.1)."""
    c = np.asarray(partition, dtype=float)
    if c.size == 0 or np.any(np.diff(c) <= 0) or not np.all(np.isfinite(c)):
        raise IdentificationError(f"{signal} partition must be finite and strictly increasing (got {c.tolist()})")
    counts = np.bincount(interval_index(x, c), minlength=c.size + 1)
    empty = np.flatnonzero(counts == 0)
    if empty.size:
        raise IdentificationError(
            f"{signal} partition interval {_interval_text(c, int(empty[0]))} holds no sample"
            " (Phi'Phi would be singular: move or drop its breakpoints)"
        )


# --------------------------------------------------------------------------- partitions


def equally_spaced_partition(x: np.ndarray, count: int = DEFAULT_BREAKPOINTS) -> np.ndarray:
    """``count`` breakpoints at the centres of ``count`` equal bins of [min x, max x].

    For u uniform on [-1, 1] and count = 10 this is paper 001's eq. 74, c = [-0.9, -0.7, ..., 0.9].
    """
    lo, hi = float(np.min(x)), float(np.max(x))
    if not hi > lo:
        raise IdentificationError(f"the signal is constant ({lo:g}): no partition of its range exists")
    return lo + (hi - lo) * (np.arange(count) + 0.5) / count


def drop_empty_intervals(x: np.ndarray, partition: np.ndarray) -> np.ndarray:
    """The partition without the breakpoints that would leave an interval (eq. 6) empty: scanning
    left to right, a breakpoint is kept only if the interval it closes holds a sample."""
    x = np.sort(np.asarray(x, dtype=float))
    kept: list[float] = []
    for c in np.asarray(partition, dtype=float):
        lower = kept[-1] if kept else -np.inf
        if np.searchsorted(x, c, side="right") > np.searchsorted(x, lower, side="right"):
            kept.append(float(c))
    if kept and x[-1] <= kept[-1]:
        kept.pop()
    if not kept:
        raise IdentificationError("the signal takes a single value: no partition of its range exists")
    return np.asarray(kept)


def default_partition(x: np.ndarray) -> np.ndarray:
    """The partition used when none is given: 10 equally spaced breakpoints over the data's
    range (eq. 74's layout), without those that would leave an interval empty (outliers)."""
    return drop_empty_intervals(x, equally_spaced_partition(x))


def default_primary_index(partition: np.ndarray) -> int:
    """The primary index used when none is given: r = max(1, floor(p / 2)), a middle breakpoint.

    Paper 001 (sec. 5.1): the accuracy is best near c_r, so r should lie in the centre of the
    region of interest. This rule gives the paper's own choices: r = 5 for eq. 74 (p = 10),
    r = 1 for c = [-0.25, 0.25] (Example 1), s = 8 for eq. 82 (q = 17, Example 2).
    """
    return max(1, np.asarray(partition).size // 2)


def refine_partition(
    estimate: PiecewiseLinearMap, sample_range: tuple[float, float], tolerance: float = 0.03, grid: int = 201
) -> np.ndarray:
    """The paper's "bootstrapping" (sec. 5.1): a parsimonious partition from a first estimate.

    Paper 001 inspects the p = 10 estimate of Example 1 and reads off a dead zone with
    breakpoints near +-0.25. Here the reading is automatic: for K = 1, 2, ... breakpoints, the
    continuous piecewise-linear function with K free breakpoints (on a ``grid``-point grid of
    ``sample_range``) that fits the estimate best in least squares is found by greedy insertion
    followed by coordinate descent on each breakpoint; the first K whose RMS misfit is at most
    ``tolerance`` times the estimate's range over ``sample_range`` gives the partition (sorted).
    Identify again with it (``drop_empty_intervals`` guards against sparsely excited ranges).
    """
    x = np.linspace(sample_range[0], sample_range[1], grid)
    f = estimate(x)
    target = tolerance * max(float(np.ptp(f)), np.finfo(float).tiny) * np.sqrt(grid)
    hinges = np.maximum(x[:, None] - x[None, 1:-1], 0.0)  # grid x candidate breakpoints
    chosen: list[int] = []
    while True:
        chosen.append(_best_breakpoint(f, x, hinges, chosen)[0])
        for _ in range(50):  # coordinate descent; converges in a few sweeps
            moved = False
            for i in range(len(chosen)):
                others = chosen[:i] + chosen[i + 1 :]
                best, error = _best_breakpoint(f, x, hinges, others)
                if best != chosen[i]:
                    chosen[i], moved = best, True
            if not moved:
                break
        if error <= target or len(chosen) == hinges.shape[1]:
            return np.sort(x[1:-1][chosen])


def _best_breakpoint(f: np.ndarray, x: np.ndarray, hinges: np.ndarray, chosen: list[int]) -> tuple[int, float]:
    """The candidate breakpoint j (not in ``chosen``) minimising the least-squares residual of f
    on [1, x, hinges[:, chosen], hinges[:, j]], and that residual's norm (by projection: with
    P the projector off the span of the fixed columns, ||P f||^2 - (h_j^T P f)^2 / ||P h_j||^2)."""
    q, _ = np.linalg.qr(np.column_stack([np.ones_like(x), x, hinges[:, chosen]]))
    rf = f - q @ (q.T @ f)
    rh = hinges - q @ (q.T @ hinges)
    norms = np.einsum("ij,ij->j", rh, rh)
    gain = np.where(norms > 1e-12, (rh.T @ rf) ** 2 / np.where(norms > 1e-12, norms, 1.0), -np.inf)
    gain[chosen] = -np.inf
    best = int(np.argmax(gain))
    return best, float(np.sqrt(max(rf @ rf - gain[best], 0.0)))


# --------------------------------------------------------------------------- the estimator


@dataclass(frozen=True, eq=False)
class PllsEstimate:
    """The blocks identified by PLLS: G = B/A with b at lags ``delay``..n, and the point-slope
    maps f (``nonlinearity``, None when f(u) = u) and h (``feedback``, None when h = 0), whose
    breakpoints are the partitions c and d, with their primary indices r and s (1-based)."""

    linear: LinearModel
    nonlinearity: PiecewiseLinearMap | None
    feedback: PiecewiseLinearMap | None
    primary_index: int | None
    feedback_primary_index: int | None
    uncertainty: Uncertainty | None = None


def rank_one_factors(
    theta_b: np.ndarray, beta: float | None, a: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(b, mu) minimising ||vec^-1(theta_B) - mu b^T||_F, eqs. 35-37.

    ``theta_b`` is vec^-1(theta_B)^T, one row per input lag (n_b x (p+1)). mu = beta sigma_1 u_1,
    b = v_1 / beta with the singular vectors' sign fixed by 1^T v_1 >= 0. ``beta`` None: the
    default of the module docstring, which needs the denominator coefficients ``a`` (lags 1..n,
    b aligned with the last lags).
    """
    left, sigma, right_t = np.linalg.svd(np.asarray(theta_b, dtype=float).T, full_matrices=False)
    u1, v1 = left[:, 0], right_t[0]
    if np.sum(v1) < 0:
        u1, v1 = -u1, -v1
    if beta is None:
        beta = _unit_gain_beta(v1, a)
    return v1 / beta, beta * sigma[0] * u1


def _unit_gain_beta(v1: np.ndarray, a: np.ndarray | None) -> float:
    """beta giving B(1)/A(1) = 1 with b = v1/beta; 1 (unit-norm b) when that gain is not finite."""
    den = 1.0 + (0.0 if a is None else float(np.sum(a)))
    scale = 1.0 + (0.0 if a is None else float(np.sum(np.abs(a))))
    if abs(np.sum(v1)) < 1e-9 or abs(den) < 1e-9 * scale:
        return 1.0
    return float(np.sum(v1)) / den


def feedback_factors(theta_a: np.ndarray, b: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """(a, nu) minimising ||vec^-1(theta_A) - (nu b^T + 1 a^T)||_F: Proposition 1, eqs. 54-61.

    ``theta_a`` is vec^-1(theta_A)^T, one row per output lag j = 1..n (n x (q+1)); ``b`` is
    aligned with those lags (zeros below the relative degree). With A = vec^-1(theta_A),
    r = b and s = 1_{q+1} in eq. 54:

        a  = A^T 1 / (q+1) + alpha b                                  (eq. 60)
        nu = (I - 1 1^T / (q+1)) A b / (b^T b) - alpha 1              (eq. 61)
    """
    big_a = np.asarray(theta_a, dtype=float).T  # (q+1) x n
    ones = np.ones(big_a.shape[0])
    a = big_a.T @ ones / ones.size + alpha * b
    nu = big_a @ b / (b @ b)
    return a, nu - nu.mean() - alpha * ones


def _regression(
    y: np.ndarray, u_channels: np.ndarray, order: int, delay: int, zeta: np.ndarray | None, runs: Runs | None = None
) -> tuple[Regression, np.ndarray]:
    """Phi of eq. 23 (zeta None: [-Phi_y, Phi_eta, 1]) or of eqs. 47 and 66 ([-Phi_zeta, Phi_u or
    Phi_eta, -1]): the shared builder, with the output columns y(k-j) replaced by the output
    basis zeta(y(k-j)) for the feedback structures; rows within ``runs``."""
    try:
        reg = build_regression(y, u_channels, order, delay, runs=runs)
    except ValueError as exc:
        raise IdentificationError(f"PLLS: {exc}") from None
    n = reg.output_lags.size
    if zeta is None:
        return reg, np.column_stack([reg.phi, np.ones(reg.rows.size)])
    phi_zeta = lagged_columns(zeta, reg.output_lags, reg.rows)
    return reg, np.column_stack([-phi_zeta, reg.phi[:, n:], -np.ones(reg.rows.size)])


def plls(
    u: np.ndarray,
    y: np.ndarray,
    order: int,
    delay: int = 1,
    structure: str = "hammerstein",
    partition: np.ndarray | None = None,
    feedback_partition: np.ndarray | None = None,
    primary_index: int | None = None,
    feedback_primary_index: int | None = None,
    beta: float | None = None,
    alpha: float = 0.0,
    gamma: float = 0.0,
    instrumental: bool = False,
    uncertainty: bool = False,
    reference: np.ndarray | None = None,
    runs: Runs | None = None,
    compiled: bool | None = None,
) -> PllsEstimate:
    """PLLS of paper 001, sec. 4 (the numbered steps at the end of 4.1, 4.2 and 4.3).

    ``instrumental`` (Hammerstein only): least squares, then ``INSTRUMENT_PASSES`` passes of
    instrumental variables (``_instrumental_step``), consistent under output noise.
    ``uncertainty``: the estimate carries its ``uncertainty.Uncertainty`` (``plls_uncertainty``).
    ``reference`` (closed loop, Hammerstein structure only): eq. 33 solved by instrumental
    variables (``_instrumental_plls``): a first IV pass with instruments [-y_r lags, eta(u_r) lags, 1]
    (u_r, y_r the reference's parts of u and y), then the refined pass of Laurain, Gilson and
    Garnier (CDC 2009) with y_r replaced by the first estimate's output simulated on u_r (no bounds).

    ``partition`` c (input map f) and ``feedback_partition`` d (feedback map h) default to
    ``default_partition`` of u and y; the primary indices r and s to ``default_primary_index``.
    ``delay`` is the relative degree: b holds b_delay..b_n (the paper has delay = 1).
    ``runs`` (several experiments laid end to end): regression rows, instruments and the IV passes'
    simulations stay within each run, every run simulated from rest.
    ``compiled``: None = the numba kernel ``plls_kernel.plls_solve`` (estimate and bounds) where it applies
    (Hammerstein with ``instrumental``, beta None, one run, no reference) and numba is available
    (``compiled_loops.numba_enabled``); False = this numpy reference, which the kernel equals to rounding.
    Raises IdentificationError when an interval of a partition holds no sample.
    """
    if structure not in STRUCTURES:
        raise ValueError(f"structure must be one of {STRUCTURES} (got {structure!r})")
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    has_input_map = structure != "feedback"
    has_feedback = structure != "hammerstein"
    c = r = d = s = eta = zeta = None
    if has_input_map:
        c = default_partition(u) if partition is None else np.asarray(partition, dtype=float)
        check_partition(u, c, "input")
        r = default_primary_index(c) if primary_index is None else primary_index
        if (compiled is not False and structure == "hammerstein" and instrumental and beta is None and reference is None
                and several(runs) is None and numba_enabled()):
            found = compiled_plls(u, y, c, r, order, delay, uncertainty)
            if found is not None:
                return found
        eta = point_slope_basis(u, c, r)
    if has_feedback:
        d = default_partition(y) if feedback_partition is None else np.asarray(feedback_partition, dtype=float)
        check_partition(y, d, "output")
        s = default_primary_index(d) if feedback_primary_index is None else feedback_primary_index
        zeta = point_slope_basis(y, d, s)

    reg, phi = _regression(y, eta if has_input_map else u, order, delay, zeta, runs)
    if reference is not None:
        if structure != "hammerstein":
            raise UsageError("--reference: only for plls-hammerstein among the PLLS structures")
        return _instrumental_plls(u, y, reg, phi, c, r, delay, beta, reference, runs)
    n, n_b = reg.output_lags.size, reg.input_lags.size

    def blocks(theta: np.ndarray) -> PllsEstimate:
        """The blocks from the lifted parameters theta~ (eqs. 32-38, 53, 60-62, 70-71)."""
        if structure == "hammerstein":  # eqs. 32-38
            return _hammerstein_factors(theta, reg, c, r, delay, beta)
        offset = theta[-1]
        theta_a = theta[: n * zeta.shape[1]].reshape(n, zeta.shape[1])
        theta_in = theta[n * zeta.shape[1] : -1].reshape(n_b, -1)
        if structure == "feedback":  # eqs. 53, 60-62
            b = theta_in[:, 0]
        else:  # eqs. 70, 37
            b, mu = rank_one_factors(theta_in, beta, theta_a.mean(axis=1))  # a of eq. 60 at alpha = 0
        a, nu = feedback_factors(theta_a, _on_output_lags(b, n), alpha)
        offset_ds = offset - d[s - 1] * np.sum(a)
        if structure == "feedback":
            lam = offset_ds / np.sum(b)  # eq. 62
            return _estimate(a, b, delay, None, (d, s, nu, lam))
        kappa = gamma - offset_ds / np.sum(b)  # eq. 71 with lambda = gamma
        return _estimate(a, b, delay, (c, r, mu, kappa), (d, s, nu, gamma))

    theta = solve_least_squares(phi, reg.target)  # eq. 33
    estimate = blocks(theta)
    z = None
    if instrumental and structure == "hammerstein":
        for _ in range(INSTRUMENT_PASSES):
            z, theta = _instrumental_step(estimate, u, eta, order, delay, phi, reg.target, z, theta, runs)
            estimate = blocks(theta)
    if not uncertainty:
        return estimate
    return replace(estimate, uncertainty=guarded(lambda: plls_uncertainty(
        blocks, theta, regression_covariance(phi, reg.target - phi @ theta, z), z is not None)))


def compiled_plls(u: np.ndarray, y: np.ndarray, partition: np.ndarray, primary: int, order: int, delay: int,
                  uncertainty: bool) -> PllsEstimate | None:
    """``plls(structure="hammerstein", instrumental=True)`` by the numba kernel ``plls_kernel.plls_solve``,
    with its bounds when ``uncertainty`` (None: left to the reference, ``plls_uncertainty``); None where
    the reference must decide about the estimate."""
    from .plls_kernel import OK, plls_solve

    arrays = [np.ascontiguousarray(x, dtype=float) for x in (u, y, partition)]
    try:
        status, a, b, mu, kappa, instrumented, bounds_status, poles_std, zeros_std, map_covariance = plls_solve(
            *arrays, int(primary), int(order), int(delay), INSTRUMENT_PASSES, bool(uncertainty))
    except (np.linalg.LinAlgError, ValueError, ZeroDivisionError):
        return None
    if status != OK:
        return None
    estimate = _estimate(a, b, delay, (partition, primary, mu, kappa), None)
    if not uncertainty:
        return estimate
    if bounds_status != OK:
        return None
    return replace(estimate, uncertainty=Uncertainty(poles_std, zeros_std, None, map_covariance, _how(instrumented)))


def _instrumental_step(estimate: PllsEstimate, u: np.ndarray, eta: np.ndarray, order: int, delay: int,
                       phi: np.ndarray, target: np.ndarray, z: np.ndarray | None,
                       theta: np.ndarray, runs: Runs | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """One pass of instrumental variables (an extension of paper 001, whose least squares is
    biased by output noise: the equation error A(q) e is coloured and correlated with the
    y(k - j) columns). The instruments are the regressors with y replaced by the noise-free
    simulation x_hat = G_hat f_hat(u) of the current estimate (the auxiliary-model IV of
    Young, Automatica 1976; Soederstroem & Stoica, *System Identification* 1989, sec. 8.2),
    uncorrelated with any noise independent of u: theta_IV = (Z^T Phi)^-1 Z^T y. Keeps
    (z, theta) when the estimate is unstable or Z^T Phi is singular."""
    if not estimate.linear.is_stable():
        return z, theta
    x_hat = per_run(lambda part: simulate_hammerstein(part, estimate.nonlinearity, estimate.linear), u, runs)
    _, instruments = _regression(x_hat, eta, order, delay, None, runs)
    normal = instruments.T @ phi
    if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > 1e12:
        return z, theta
    return instruments, np.linalg.solve(normal, instruments.T @ target)


def plls_uncertainty(blocks, theta: np.ndarray, covariance: np.ndarray, instrumental: bool) -> Uncertainty:
    """The sds of a PLLS estimate: Cov(theta~) by batch means (``uncertainty``), propagated through
    the block recovery (rank-1 factors, Proposition 1) to the poles, zeros and the input map's
    knot values and outer slopes."""
    nominal = blocks(theta).nonlinearity
    pack = None if nominal is None else map_parameters(nominal).pack

    def figures(t: np.ndarray):
        est = blocks(t)
        return est.linear.poles, est.linear.zeros, np.zeros(0) if pack is None else pack(est.nonlinearity)

    poles_std, zeros_std, map_covariance = propagate(figures, theta, covariance)
    return Uncertainty(poles_std, zeros_std, None, None if pack is None else map_covariance, _how(instrumental))


def _how(instrumental: bool) -> str:
    """``Uncertainty.how`` of a PLLS estimate."""
    return ("plls: " + ("instrumental variables" if instrumental else "least squares")
            + ", batch means of the influences, first-order propagation")


def _hammerstein_factors(theta: np.ndarray, reg: Regression, c, r, delay: int, beta) -> PllsEstimate:
    """The blocks of the Hammerstein theta~ (eqs. 32-38)."""
    a = theta[: reg.output_lags.size]
    b, mu = rank_one_factors(reg.split(theta[:-1])[1], beta, a)
    return _estimate(a, b, delay, (c, r, mu, theta[-1] / np.sum(b)), None)  # kappa: eq. 38


def _instrumental_plls(u, y, reg: Regression, phi: np.ndarray, c, r, delay: int, beta,
                       reference: np.ndarray, runs: Runs | None = None) -> PllsEstimate:
    """PLLS-Hammerstein by (refined) instrumental variables, see ``plls``."""
    u_r = reference_part(u, reference, runs=runs)
    input_instruments = lagged_columns(point_slope_basis(u_r, c, r), reg.input_lags, reg.rows)
    n = reg.output_lags.size

    def instruments(output: np.ndarray) -> np.ndarray:
        return np.column_stack([-lagged_columns(output, reg.output_lags, reg.rows), input_instruments,
                                np.ones(reg.rows.size)])
    estimate = _hammerstein_factors(solve_instrumental(phi, reg.target, instruments(reference_part(y, reference,
                                                                                                  runs=runs))),
                                    reg, c, r, delay, beta)
    if estimate.linear.is_stable():  # refined: the noise-free output of the first estimate
        simulated = per_run(lambda part: simulate_hammerstein(part, estimate.nonlinearity, estimate.linear), u_r, runs)
        if np.all(np.isfinite(simulated)) and np.std(simulated[n:]) > 0:
            estimate = _hammerstein_factors(solve_instrumental(phi, reg.target, instruments(simulated)),
                                            reg, c, r, delay, beta)
    return estimate


def _on_output_lags(b: np.ndarray, order: int) -> np.ndarray:
    """b_delay..b_n padded with zeros to lags 1..n."""
    return np.concatenate([np.zeros(order - b.size), b])


def _estimate(a, b, delay: int, input_map: tuple | None, feedback_map: tuple | None) -> PllsEstimate:
    """The estimate from a, b and the point-slope parameters (partition, primary index, slopes,
    value at the primary breakpoint) of f and h (None: absent)."""
    f, h = (None if parts is None else point_slope_map(*parts) for parts in (input_map, feedback_map))
    return PllsEstimate(
        LinearModel(np.concatenate([np.zeros(delay), b]), np.concatenate([[1.0], a])), f, h,
        None if input_map is None else input_map[1], None if feedback_map is None else feedback_map[1],
    )


def identify_plls(
    v: np.ndarray,
    y: np.ndarray,
    options: IdentifyOptions,
    structure: str = "hammerstein",
    beta: float | None = None,
    alpha: float = 0.0,
    gamma: float = 0.0,
) -> IdentificationResult:
    """``identify --method plls-hammerstein | plls-feedback | plls-hammerstein-feedback``.

    ``options.order`` and ``options.delay`` set n and the relative degree. ``options.partition``
    is c, the partition of the input map f; ``options.feedback_partition`` is d, that of the
    feedback map h (for ``feedback``, whose only map is h, ``options.partition`` is accepted as d
    too). Unset partitions: ``default_partition`` of the data (10 equally spaced breakpoints).
    ``beta``, ``alpha``, ``gamma``: see the module docstring. Hammerstein: least squares, then instrumental
    variables (``plls(instrumental=True)``); every structure reports its ``uncertainty`` (with a reference:
    the refined IV of ``plls(reference=...)``, without bounds).
    """
    given = None if options.partition is None else np.asarray(options.partition, dtype=float)
    feedback_given = options.feedback_partition
    if structure == "hammerstein" and feedback_given is not None:
        raise UsageError("--feedback-partition: only for plls-feedback and plls-hammerstein-feedback")
    if structure == "feedback":
        partition, feedback_given = None, given if feedback_given is None else feedback_given
    else:
        partition = given
    est = plls(
        v, y, options.order, options.delay, structure,
        partition=partition, feedback_partition=feedback_given, beta=beta, alpha=alpha, gamma=gamma,
        instrumental=options.reference is None, uncertainty=options.reference is None,
        reference=check_reference(options.reference, np.size(v)), runs=options.runs,
    )
    if est.feedback is None:
        def simulate(x: np.ndarray) -> np.ndarray:
            return simulate_hammerstein(x, est.nonlinearity, est.linear)
    elif est.nonlinearity is None:
        def simulate(x: np.ndarray) -> np.ndarray:
            return simulate_feedback(x, est.feedback, est.linear)
    else:
        def simulate(x: np.ndarray) -> np.ndarray:
            return simulate_hammerstein_feedback(x, est.nonlinearity, est.feedback, est.linear)

    details = {"structure": structure, "beta": beta, "alpha": alpha, "gamma": gamma,
               "estimator": ("instrumental_variables (reference)" if options.reference is not None
                             else "instrumental_variables" if structure == "hammerstein" else "least_squares")}
    if est.nonlinearity is not None:
        details.update(partition=est.nonlinearity.breakpoints.tolist(), primary_index=est.primary_index)
    if est.feedback is not None:
        details.update(feedback_partition=est.feedback.breakpoints.tolist(),
                       feedback_primary_index=est.feedback_primary_index)
    return IdentificationResult(
        method="plls-" + structure.replace("_", "-"),
        linear=est.linear,
        simulate=simulate,
        order=options.order,
        nonlinearity=est.nonlinearity,
        feedback_nonlinearity=est.feedback,
        extra={"plls": details},
        uncertainty=est.uncertainty,
    )
