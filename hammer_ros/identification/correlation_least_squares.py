"""Paper 000 (Lum & Bernstein): correlation least squares (CLS), Bai's two-stage nonlinear
least squares (NLS) and standard least squares (LS) for the Hammerstein model
y = G(q) F[v], each with the ARX (eq. 1) or the mu-Markov (eq. 3) structure of G.

Poles and zeros: ARX directly from the estimated (a_j, b_i); mu-Markov from the estimated
Markov parameters h_d .. h_(d+mu-1) via ERA (``hammer_ros.identification.era``; paper 000 footnote 1,
Juang 1994), as the paper does, at the known order n and relative degree d.

Gain: every result's ``gain`` is h_d_hat, the first non-zero Markov parameter of the
identified linear block when the identified nonlinearity is normalised to unit slope
(gamma_1 = 1). The paper's "Gain" column is h_d_hat / h_d (h_d of the true plant); it is not
the static gain. ``markov`` holds h_0 .. h_(d+mu-1) of the identified linear block (estimated
directly for mu-Markov, the impulse response of the ARX model for ARX).

Defaults (documented choices, the paper leaves them open):

* mu = 30 Markov parameters (paper 000 sec. 4).
* tau_max, the largest correlation lag of CLS (eq. 8), ``default_tau_max``: max(15, 3n) for
  ARX and 2 (mu + n) for mu-Markov (66 for mu = 30, n = 3). The step-1 regression runs over
  the 2 tau_max + 1 correlation lags. mu-Markov needs its mu + n - 1 lags plus enough rows
  (tau_max well above mu + n; paper Fig. 7 shows it failing at 2 tau_max + 1 < 31); with
  2 (mu + n) it has 3 (mu + n) + 2 rows for mu + 2n - 1 parameters. ARX, with only 2n
  parameters, is better off without the long tail of the correlation functions, where the
  impulse response has decayed and only estimation error is left: on G1 and G2 (paper 000
  Tables 1-4, 6) the pole/zero RSS is lowest for tau_max = 15-20 and grows beyond (the zero
  at 0.5 drifts to 0.47 at tau_max = 30); below ~3n there are too few rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Literal

import numpy as np

from ..errors import IdentificationError
from .compiled_loops import numba_enabled
from .correlation import auto_correlation, cross_correlation
from .era import eigensystem_realization
from .instrumental import check_reference, reference_part, solve_instrumental
from .linear import LinearModel
from .piecewise_linear_ls import check_partition, default_primary_index, point_slope_basis, point_slope_map
from .regression import (
    Regression,
    filtered_basis,
    filtered_output,
    fit_regression,
    largest_lag,
    least_squares_qr,
    markov_lags,
    polynomial_basis,
)
from .result import IdentificationResult
from .runs import Runs, several
from .simulate import simulate_hammerstein
from .static_maps import PiecewiseLinearMap, PolynomialMap, map_parameters
from .uncertainty import CLS_HOW, Uncertainty, cls_uncertainty, era_root_std, guarded, propagate, regression_covariance

DEFAULT_MU = 30
STRUCTURES = ("arx", "markov")


@dataclass(frozen=True, eq=False)
class LinearEstimate:
    """An identified linear block: the model (ARX, or the ERA realisation of the mu-Markov
    estimate), its Markov parameters h_0 .. h_(d+mu-1), and the raw regression solution
    (a_j or alpha_j; b_i or h_i, beta_i) in the lag order of ``regression.markov_lags``."""

    linear: LinearModel
    markov: np.ndarray
    denominator: np.ndarray
    numerator: np.ndarray
    delay: int
    mu: int

    @property
    def first_markov(self) -> float:
        """h_d, the first non-zero Markov parameter (d = the relative degree)."""
        return float(self.markov[self.delay])

    def scaled(self, factor: float) -> LinearEstimate:
        return LinearEstimate(self.linear.scaled(factor), self.markov * factor, self.denominator,
                              self.numerator * factor, self.delay, self.mu)


@dataclass(frozen=True, eq=False)
class HammersteinEstimate:
    """y = G(q) F[v] with F a polynomial (ascending coefficients from v^0) of unit slope
    gamma_1 = 1, so that ``linear.first_markov`` is the paper's gain figure h_d_hat (or a
    piecewise-linear F of unit Bussgang gain, ``piecewise_linear_step``)."""

    linear: LinearEstimate
    nonlinearity: PolynomialMap | PiecewiseLinearMap | None


def _check_record(v: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(v, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    if v.size != y.size:
        raise IdentificationError(f"input and output differ in length ({v.size} vs {y.size})")
    return v, y


def _least_squares_fit(y: np.ndarray, v: np.ndarray, order: int, delay: int, mu: int, intercept: bool = False,
                       runs: Runs | None = None):
    """Solve the ARX (mu = 1) or mu-Markov regression (eqs. 1, 3) of y on v (1-D or a basis
    matrix; rows within ``runs``): returns (regression, a or alpha, input coefficients as lags x channels)."""
    reg, theta = fit_regression(y, v, order, delay, mu, intercept, runs)
    a, coefficients = reg.split(theta)
    return reg, a, coefficients


def linear_estimate(a: np.ndarray, numerator: np.ndarray, order: int, delay: int, mu: int) -> LinearEstimate:
    """The linear block from regression coefficients: ARX (mu = 1) directly as
    B(q^-1)/A(q^-1) of eq. (2); mu-Markov (mu > 1) by ERA of order n from the estimated
    Markov parameters h_d .. h_(d+mu-1) of eq. (3) (paper 000 footnote 1)."""
    numerator = np.asarray(numerator, dtype=float)
    if mu == 1:
        linear = LinearModel(np.concatenate([np.zeros(delay), numerator]), np.concatenate([[1.0], a]))
        markov = linear.markov_parameters(delay + DEFAULT_MU)
    else:
        markov = np.concatenate([np.zeros(delay), numerator[:mu]])
        linear = eigensystem_realization(markov, order).to_linear_model(delay)
    return LinearEstimate(linear, markov, np.asarray(a, dtype=float), numerator, delay, mu)


def _mu(structure: str, mu: int | None) -> int:
    if structure not in STRUCTURES:
        raise IdentificationError(f"structure must be one of {STRUCTURES}, got {structure!r}")
    return 1 if structure == "arx" else (DEFAULT_MU if mu is None else int(mu))


def default_tau_max(order: int, mu: int = 1) -> int:
    """max(15, 3 order) for ARX (mu = 1), 2 (mu + order) for mu-Markov (module docstring)."""
    return max(15, 3 * order) if mu == 1 else 2 * (mu + order)


# --- standard least squares (sec. 3.3) -------------------------------------------------------


def standard_least_squares(v: np.ndarray, y: np.ndarray, order: int, delay: int, mu: int = 1,
                           runs: Runs | None = None) -> LinearEstimate:
    """Standard LS, paper 000 sec. 3.3: ignore F and fit the ARX (mu = 1, eq. 1) or mu-Markov
    (eq. 3) model to the raw pairs (v(k), y(k)). Its h_d_hat estimates C_F h_d only for
    mu-Markov with a long enough mu (the y-lags correlate with the unmodelled distortion)."""
    v, y = _check_record(v, y)
    _, a, coefficients = _least_squares_fit(y, v, order, delay, mu, runs=runs)
    return linear_estimate(a, coefficients[:, 0], order, delay, mu)


# --- correlation least squares (sec. 3.1) ----------------------------------------------------


def correlation_functions(v: np.ndarray, y: np.ndarray, tau_max: int,
                          runs: Runs | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(phi_vv, phi_yv) for tau = -tau_max .. tau_max, paper 000 eq. (8) (Remark 2: the record
    holds N + 2 tau_max + 1 samples, every lag averages the same N + 1 products; with ``runs``
    the products of every run's own centres)."""
    v, y = _check_record(v, y)
    try:
        return auto_correlation(v, tau_max, runs), cross_correlation(v, y, tau_max, runs)
    except ValueError as exc:
        raise IdentificationError(f"tau_max {tau_max}: {exc}") from None


def gain_correction(
    v: np.ndarray, y: np.ndarray, step1: LinearEstimate, order: int, delay: int, poly: int = 3,
    basis: np.ndarray | None = None, instrument_basis: np.ndarray | None = None, runs: Runs | None = None,
) -> np.ndarray:
    """CLS step 2 (paper 000 sec. 3.1): gamma_1 .. gamma_p of

        A_hat(q^-1) y(k) = B_hat(q^-1) [gamma_1 v(k) + ... + gamma_p v^p(k)] + e(k),

    by least squares on the raw record, with (A_hat, B_hat) the step-1 ARX polynomials or the
    ARMARKOV polynomials of eq. (4) (alpha_j, h_i, beta_i) for mu-Markov, at the lags of
    ``regression.markov_lags``. The regressors are the basis v^0, v, ..., v^p filtered by the
    FIR B_hat, the target is y filtered by A_hat (rows from the largest lag on, as the shared
    regression builder would give them, without forming its W x (n + (p+1)(mu+n)) matrix).

    Offsets (an extension of the paper, which assumes a zero-mean input): a constant gamma_0
    is estimated with gamma_1..gamma_p, so a command with a non-zero mean or a sensor offset
    does not bias F; the returned array is gamma_0..gamma_p.

    ``basis`` (N x q, its first column the constant) replaces the monomials 1, v, ..., v^p:
    the paper's step 2 is linear in any basis functions of v, e.g. the point-slope basis of
    paper 001 (``piecewise_linear_step``).

    ``instrument_basis`` (the same basis of a noise-free input, e.g. ``instrumental.reference_part``
    of v in closed loop): the regressors' instruments, filtered alike; theta then solves the IV
    system of ``instrumental.solve_instrumental`` instead of the least squares (the equation error
    A_hat w is uncorrelated with them).

    ``runs``: only the rows whose lags stay in their run (``step_two_rows``)."""
    try:
        output_lags, input_lags = markov_lags(order, delay, step1.mu)
    except ValueError as exc:
        raise IdentificationError(f"CLS step 2: {exc}") from None
    first = largest_lag(order, step1.mu)
    if basis is None:
        basis = polynomial_basis(v, poly, constant=True)
    if v.size <= first + basis.shape[1]:
        raise IdentificationError(f"CLS step 2: {v.size} samples are too few for lags up to {first}")
    numerator = np.zeros(first + 1)
    numerator[input_lags] = step1.numerator
    keep = step_two_rows(first, runs)
    target = filtered_output(y, output_lags, step1.denominator)[first:][keep]  # A_hat(q^-1) y
    if target.size <= basis.shape[1]:
        raise IdentificationError(f"CLS step 2: {keep.size} rows within the runs are too few for lags up to {first}")
    if instrument_basis is not None:
        return solve_instrumental(filtered_basis(basis, numerator)[keep], target,
                                  filtered_basis(instrument_basis, numerator)[keep])
    return least_squares_qr(filtered_basis(basis, numerator)[keep], target)


def step_two_rows(first: int, runs: Runs | None) -> slice | np.ndarray:
    """The rows of CLS step 2's arrays (sample k = first + row) whose lags up to ``first`` stay in
    their run: all (a slice) without several runs, else ``Runs.rows(first) - first``."""
    runs = several(runs)
    return slice(None) if runs is None else runs.rows(first) - first


def correlation_least_squares(
    v: np.ndarray, y: np.ndarray, order: int, delay: int, mu: int = 1, tau_max: int | None = None, poly: int = 3
) -> HammersteinEstimate:
    """Correlation least squares (CLS), paper 000 sec. 3.1, on the record (v, y): the
    correlation functions of eq. (8) up to ``tau_max`` (None = ``default_tau_max``), then
    ``correlation_least_squares_steps``."""
    tau_max = default_tau_max(order, mu) if tau_max is None else int(tau_max)
    phi_vv, phi_yv = correlation_functions(v, y, tau_max)
    return correlation_least_squares_steps(phi_vv, phi_yv, v, y, order, delay, mu, poly)


def correlation_least_squares_steps(
    phi_vv: np.ndarray, phi_yv: np.ndarray, v: np.ndarray, y: np.ndarray, order: int, delay: int, mu: int = 1,
    poly: int = 3, partition: np.ndarray | None = None, instrument: np.ndarray | None = None,
    runs: Runs | None = None,
) -> HammersteinEstimate:
    """CLS steps 1 and 2 (paper 000 sec. 3.1) from given correlation functions (indexed by
    tau + tau_max, e.g. the streaming engine's window sums) and the raw record for step 2.

    Step 1: with a separable input (Gaussian, sinusoid, phase-modulated sinusoid), Lemma 2
    (eq. 7) gives phi_yv = C_F h * phi_vv, so the ARX / mu-Markov regression (the shared
    builder) applied to the correlation functions as "input-output" data,

        phi_yv(k) = -sum_j a_j phi_yv(k-j) + sum_i b_i phi_vv(k-i)        (and eq. 3 likewise),

    over k = tau = -tau_max .. tau_max identifies h_hat = C_F h without knowing F.
    Step 2 (``gain_correction``): gamma_0..gamma_p with the step-1 (A_hat, B_hat); then
    B = s B_hat and F = (gamma_0 + gamma_1 v + ... + gamma_p v^p) / s with s = F'(mean v),
    i.e. F has unit slope at the operating point (for the paper's zero-mean input this is its
    monic F, gamma_1 = 1).

    Offsets (an extension; the paper assumes zero-mean signals): step 1 carries an intercept,
    which makes (a, b) invariant to constant offsets of both correlation functions. A Gaussian
    input N(m, s^2) gives raw correlations phi_vv + m^2 and phi_yv + m E{y}, so the intercept
    reproduces the centred-signal estimate (Bussgang/Nuttall holds for v - m) while the
    estimator stays the paper's eq. (8) - which the streaming engine updates recursively.

    With ``partition`` F is piecewise linear on those breakpoints instead (``piecewise_linear_step``).

    Closed loop (``instrumental``): given phi_vr, phi_yr (the correlations with the reference)
    as ``phi_vv``, ``phi_yv`` and the reference's part of v as ``instrument``, step 1 is the same
    regression and step 2 the IV solve with the basis of ``instrument`` as instruments.

    ``runs`` (several experiments; the correlations then made with ``runs`` too): step 2's rows
    stay within the runs (``gain_correction``).
    """
    v, y = _check_record(v, y)
    phi_vv, phi_yv = _check_record(phi_vv, phi_yv)
    _, a, coefficients = _least_squares_fit(phi_yv, phi_vv, order, delay, mu, intercept=True)
    step1 = linear_estimate(a, coefficients[:, 0], order, delay, mu)
    if partition is not None:
        return piecewise_linear_step(v, y, step1, order, delay, np.asarray(partition, dtype=float), instrument, runs)
    gamma = gain_correction(v, y, step1, order, delay, poly, instrument_basis=None if instrument is None
                            else polynomial_basis(instrument, poly, constant=True), runs=runs)
    mean, slope, coefficients = float(v.sum() / v.size), 0.0, gamma.tolist()  # v.mean()
    for power in range(gamma.size - 1, 0, -1):  # F'(mean v) = sum_l l gamma_l mean^(l-1) by Horner's rule
        slope = slope * mean + power * coefficients[power]
    if abs(slope) < 1e-12 * max(1.0, *map(abs, coefficients)):
        raise IdentificationError("CLS step 2: F has zero slope at the input mean; the linear block's gain is "
                                  "not identifiable")
    return HammersteinEstimate(step1.scaled(slope), PolynomialMap(gamma / slope))


def piecewise_linear_step(
    v: np.ndarray, y: np.ndarray, step1: LinearEstimate, order: int, delay: int, partition: np.ndarray,
    instrument: np.ndarray | None = None, runs: Runs | None = None,
) -> HammersteinEstimate:
    """CLS step 2 with a piecewise-linear F (an extension: paper 000's step 2 in the
    point-slope basis of paper 001, eqs. 8-11): F(v) = eta(v)^T m + kappa on ``partition``
    by least squares given the step-1 (A_hat, B_hat) (``gain_correction``). Step 1 needs no
    assumption on F (Lemma 2), so the poles and zeros are those of the polynomial variant,
    while F may have the corners of a dead zone, a saturation or a relay. F is normalised to
    unit Bussgang gain cov(F(v), v) / var(v) (its slope at the operating point may be zero,
    e.g. inside a dead zone), B = s B_hat accordingly."""
    check_partition(v, partition, "input")
    primary = default_primary_index(partition)
    eta = point_slope_basis(v, partition, primary)
    instruments = None if instrument is None else np.column_stack(
        [np.ones(v.size), point_slope_basis(instrument, partition, primary)])
    theta = gain_correction(v, y, step1, order, delay, basis=np.column_stack([np.ones(v.size), eta]),
                            instrument_basis=instruments, runs=runs)
    f = eta @ theta[1:] + theta[0]
    centred = v - v.mean()
    scale = float(centred @ (f - f.mean()) / (centred @ centred))
    if abs(scale) < 1e-12 * max(1.0, float(np.max(np.abs(theta)))):
        raise IdentificationError("CLS step 2: F is uncorrelated with the input; the linear block's gain is "
                                  "not identifiable")
    return HammersteinEstimate(step1.scaled(scale), point_slope_map(partition, primary, theta[1:] / scale,
                                                                     float(theta[0] / scale)))


# --- Bai's two-stage nonlinear least squares (sec. 3.2) --------------------------------------


def bai_two_stage_nls(
    v: np.ndarray, y: np.ndarray, order: int, delay: int, mu: int = 1, poly: int = 3, runs: Runs | None = None
) -> HammersteinEstimate:
    """Bai's two-stage NLS (Bai 1998; paper 000 sec. 3.2, eqs. 9-12), monomials f_l = v^l.

    Stage 1: least squares on eq. (10), theta = (a_1..a_n, b_i gamma_l lag-major), i.e. the
    shared builder with the basis matrix [v, v^2, ..., v^p] (mu-Markov: eq. 3 with every
    input coefficient h_i, beta_i multiplied by gamma_l).
    Stage 2: Theta_bgamma (input lags x p) = sum sigma_i U_i V_i^T; the rank-one part
    sigma_1 U_1 V_1^T = b gamma^T with Remark 3's normalisation gamma_1 = 1 (eq. 12):

        gamma_hat = V_1 / V_11,   b_hat = sigma_1 V_11 U_1.

    Eq. (12) reads "b_hat = U_1/sigma_1 V_11" in the text; the reading sigma_1 V_11 U_1 is the
    one with b_hat gamma_hat^T = sigma_1 U_1 V_1^T, and it reproduces Table 1 (exact for F_1).
    """
    v, y = _check_record(v, y)
    _, a, lumped = _least_squares_fit(y, polynomial_basis(v, poly), order, delay, mu, runs=runs)
    return _nls_stage_two(a, lumped, order, delay, mu)


def _nls_stage_two(a: np.ndarray, lumped: np.ndarray, order: int, delay: int, mu: int) -> HammersteinEstimate:
    """Stage 2 of ``bai_two_stage_nls``: the rank-one factors b_hat, gamma_hat of Theta_bgamma (eq. 12)."""
    b_hat, coefficients = _rank_one(lumped)
    return HammersteinEstimate(linear_estimate(a, b_hat, order, delay, mu), PolynomialMap(coefficients))


def _rank_one(lumped: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(b_hat, F's coefficients [0, gamma_hat]) from Theta_bgamma by eq. 12 (``bai_two_stage_nls``)."""
    u, s, vt = np.linalg.svd(lumped, full_matrices=False)
    v11 = vt[0, 0]
    if s[0] == 0.0 or abs(v11) < 1e-12:
        raise IdentificationError("NLS stage 2: the linear term of F is not identifiable (V_11 = 0)")
    return s[0] * v11 * u[:, 0], np.concatenate([[0.0], vt[0] / v11])


# --- the registry's entry points (hammer_ros.identification.methods) ----------------------------------------


def _result(method: str, estimate: HammersteinEstimate, order: int, extra: dict,
            uncertainty: Uncertainty | None = None) -> IdentificationResult:
    """The result of an estimate; picklable (its simulator a bound method or a partial, not a closure),
    so that a ``SolverProcess`` can be handed a CLS estimate made elsewhere."""
    linear, nonlinearity = estimate.linear, estimate.nonlinearity
    simulate = (linear.linear.simulate if nonlinearity is None
                else partial(simulate_hammerstein, nonlinearity=nonlinearity, linear=linear.linear))
    return IdentificationResult(
        method=method,
        linear=linear.linear,
        simulate=simulate,
        order=order,
        gain=linear.first_markov,
        nonlinearity=nonlinearity,
        markov=linear.markov,
        extra=extra,
        uncertainty=uncertainty,
    )


def identify_cls(v: np.ndarray, y: np.ndarray, options, structure: str = "arx") -> IdentificationResult:
    """``cls-arx`` / ``cls-markov``: CLS with the options' order, delay, mu (default 30),
    tau_max (default ``default_tau_max``) and poly, or a piecewise-linear F on the options'
    partition when it is given (``piecewise_linear_step``). With ``options.reference`` (closed
    loop) the correlations are with the reference and step 2 is an IV solve (``instrumental``)."""
    mu = _mu(structure, options.mu)
    tau_max = default_tau_max(options.order, mu) if options.tau_max is None else options.tau_max
    reference, runs = check_reference(options.reference, np.size(v)), options.runs
    if reference is None:
        phi_vv, phi_yv = correlation_functions(v, y, tau_max, runs)
        return cls_from_correlations(phi_vv, phi_yv, v, y, options, structure, compiled="bounds")
    try:
        phi_vr, phi_yr = (cross_correlation(reference, x, tau_max, runs) for x in _check_record(v, y))
    except ValueError as exc:
        raise IdentificationError(f"tau_max {tau_max}: {exc}") from None
    return cls_from_correlations(phi_vr, phi_yr, v, y, options, structure,
                                 instrument=reference_part(v, reference, runs=runs))


def cls_from_correlations(
    phi_vv: np.ndarray, phi_yv: np.ndarray, v: np.ndarray, y: np.ndarray, options, structure: str = "arx",
    instrument: np.ndarray | None = None, compiled: bool | Literal["bounds"] | None = None,
) -> IdentificationResult:
    """``identify_cls`` on given correlation functions (tau_max = (len - 1) / 2), e.g. the
    streaming engine's window sums; (v, y) is the raw window for step 2 (``instrument``: see
    ``correlation_least_squares_steps``; ``options.runs``: the runs of (v, y), the correlations
    made with them).

    ``compiled``: None = the numba kernel ``cls_kernel.cls_solve`` for the estimate and its bounds
    where it applies (a polynomial F, no instrument) and numba is available
    (``compiled_loops.numba_enabled``): what the streaming engine solves with; False = the numpy
    reference; "bounds" = the reference's estimate (bit for bit: ``identify`` and ``reproduce``
    print it to the last digit) with the kernel's bounds (equal to the reference's to rounding).
    Several runs: the reference (the kernel's step 2 takes one continuous record)."""
    mu = _mu(structure, options.mu)
    extra = ({"tau_max": (np.size(phi_vv) - 1) // 2} | ({"mu": mu} if mu > 1 else {})
             | ({"instrument": "reference"} if instrument is not None else {}))
    estimate = uncertainty = None
    if (compiled is not False and instrument is None and options.partition is None and several(options.runs) is None
            and numba_enabled()):
        estimate, uncertainty = compiled_steps(phi_vv, phi_yv, v, y, options.order, options.delay, mu,
                                               options.poly) or (None, None)
    if estimate is None or compiled == "bounds":
        estimate = correlation_least_squares_steps(phi_vv, phi_yv, v, y, options.order, options.delay, mu,
                                                   options.poly, options.partition, instrument, options.runs)
    if instrument is not None:  # the bounds' influences are those of the correlations with v, not with r
        return _result(f"cls-{structure}", estimate, options.order, extra)
    if uncertainty is None:
        partition = None if options.partition is None else np.asarray(options.partition, dtype=float)
        uncertainty = guarded(lambda: cls_uncertainty(phi_vv, phi_yv, v, y, options.order, options.delay, mu,
                                                      *_step_two_map(np.asarray(v, dtype=float), options.poly,
                                                                     partition), runs=options.runs))
    return _result(f"cls-{structure}", estimate, options.order, extra, uncertainty)


def compiled_steps(phi_vv: np.ndarray, phi_yv: np.ndarray, v: np.ndarray, y: np.ndarray, order: int, delay: int,
                   mu: int, poly: int, bounds: bool = True) -> tuple[HammersteinEstimate, Uncertainty | None] | None:
    """``correlation_least_squares_steps`` (a polynomial F) and, with ``bounds``, its ``cls_uncertainty`` by
    the numba kernel ``cls_kernel.cls_solve``: (estimate, bounds), the bounds None without ``bounds`` or
    where the kernel leaves them to the reference; None where the reference must decide about the
    estimate (it raises or takes another branch)."""
    from .cls_kernel import OK, cls_solve

    arrays = [np.ascontiguousarray(x, dtype=float).ravel() for x in (phi_vv, phi_yv, v, y)]
    if arrays[0].size != arrays[1].size or arrays[2].size != arrays[3].size:
        return None
    try:
        (status, a, coefficients, numerator, denominator, gamma, slope, bounds_status, poles_std, zeros_std, gain_std,
         map_covariance, blocks) = cls_solve(*arrays, int(order), int(delay), int(mu), int(poly), bool(bounds))
    except (np.linalg.LinAlgError, ValueError, ZeroDivisionError):
        return None
    if status != OK:
        return None
    if mu == 1:
        linear = linear_estimate(a, coefficients, order, delay, mu).scaled(slope)
    else:  # LinearEstimate(LinearModel(numerator, denominator), ...).scaled(slope) in one (denominator[0] = 1)
        markov = np.concatenate([np.zeros(delay), coefficients[:mu]]) * slope
        linear = LinearEstimate(LinearModel(numerator * slope, denominator), markov, a, coefficients * slope, delay, mu)
    estimate = HammersteinEstimate(linear, PolynomialMap(gamma / slope))
    if bounds_status != OK:
        return estimate, None
    return estimate, Uncertainty(poles_std, zeros_std, float(gain_std), map_covariance, CLS_HOW.format(blocks=blocks))


def _step_two_map(v: np.ndarray, poly: int, partition: np.ndarray | None):
    """For ``cls_uncertainty``: step 2's basis of v (the constant first) and gamma -> (s, the packed
    parameters of the unit map gamma / s), s = F'(mean v) for the polynomial (``correlation_least_squares_steps``),
    the Bussgang gain cov(F(v), v) / var(v) for a piecewise-linear F (``piecewise_linear_step``)."""
    if partition is None:
        powers = np.arange(poly + 1) * v.mean() ** np.maximum(np.arange(poly + 1) - 1, 0)

        def polynomial(gamma: np.ndarray) -> tuple[float, np.ndarray]:  # F'(mean) = sum_l l gamma_l mean^(l-1)
            scale = float(powers @ gamma)
            return scale, gamma / scale

        return polynomial_basis(v, poly, constant=True), polynomial
    primary = default_primary_index(partition)
    eta = point_slope_basis(v, partition, primary)
    centred = v - v.mean()
    bussgang = eta.T @ centred / (centred @ centred)  # cov(eta(v), v) / var(v), per slope

    def piecewise(theta: np.ndarray) -> tuple[float, np.ndarray]:
        scale = float(bussgang @ theta[1:])
        fmap = point_slope_map(partition, primary, theta[1:] / scale, float(theta[0] / scale))
        return scale, map_parameters(fmap).pack(fmap)

    return np.column_stack([np.ones(v.size), eta]), piecewise


def identify_nls(v: np.ndarray, y: np.ndarray, options, structure: str = "arx") -> IdentificationResult:
    """``nls-arx`` / ``nls-markov``: ``bai_two_stage_nls`` with monomials up to ``poly``."""
    mu = _mu(structure, options.mu)
    v, y = _check_record(v, y)  # bai_two_stage_nls, its regression kept for the bounds
    reg, a, lumped = _least_squares_fit(y, polynomial_basis(v, options.poly), options.order, options.delay, mu,
                                        runs=options.runs)
    estimate = _nls_stage_two(a, lumped, options.order, options.delay, mu)
    uncertainty = guarded(_regression_uncertainty, reg, np.concatenate([a, lumped.ravel()]), options.order,
                          options.delay, mu, _rank_one)
    return _result(f"nls-{structure}", estimate, options.order, {"mu": mu} if mu > 1 else {}, uncertainty)


def identify_ls(v: np.ndarray, y: np.ndarray, options, structure: str = "arx") -> IdentificationResult:
    """``ls-arx`` / ``ls-markov``: ``standard_least_squares`` (no nonlinearity)."""
    mu = _mu(structure, options.mu)
    v, y = _check_record(v, y)  # standard_least_squares, its regression kept for the bounds
    reg, a, coefficients = _least_squares_fit(y, v, options.order, options.delay, mu, runs=options.runs)
    estimate = HammersteinEstimate(linear_estimate(a, coefficients[:, 0], options.order, options.delay, mu), None)
    uncertainty = guarded(_regression_uncertainty, reg, np.concatenate([a, coefficients.ravel()]), options.order,
                          options.delay, mu, lambda coefficients: (coefficients[:, 0], None))
    return _result(f"ls-{structure}", estimate, options.order, {"mu": mu} if mu > 1 else {}, uncertainty)


def _regression_uncertainty(reg: Regression, theta: np.ndarray, order: int, delay: int, mu: int,
                            factors: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]) -> Uncertainty:
    """The bounds of a raw-data regression estimate (LS, NLS): the batch-means sandwich of the
    least-squares fit ``theta`` of ``reg`` (``uncertainty.regression_covariance``), propagated through
    ``factors`` (input coefficients -> (numerator h_d.., map coefficients or None)) to the gain h_d,
    the map and the roots: of (A, B) for ARX; for mu-Markov the Markov taps' covariance goes
    through ERA by ``era_root_std``. The intervals hold the estimator's spread, not its bias: LS
    ignores F, and both fit an equation error that output noise makes coloured and correlated
    with the y-lags."""
    covariance = regression_covariance(reg.phi, reg.target - reg.phi @ theta)
    has_map = factors(reg.split(theta)[1])[1] is not None

    def figures(t: np.ndarray):
        a, coefficients = reg.split(t)
        numerator, fmap = factors(coefficients)
        others = np.concatenate([numerator[:mu] if mu > 1 else [], [numerator[0]], fmap if has_map else []])
        if mu > 1:
            return np.zeros(0), np.zeros(0), others
        model = LinearModel(np.concatenate([np.zeros(delay), numerator]), np.concatenate([[1.0], a]))
        return model.poles, model.zeros, others

    poles_std, zeros_std, others = propagate(figures, theta, covariance)
    if mu > 1:
        numerator = factors(reg.split(theta)[1])[0]
        markov = np.concatenate([np.zeros(delay), numerator[:mu]])
        poles_std, zeros_std = era_root_std(markov, order, delay, others[:mu, :mu])
        others = others[mu:, mu:]
    return Uncertainty(poles_std, zeros_std, float(np.sqrt(others[0, 0])), others[1:, 1:] if has_map else None,
                       "least squares: batch means of the influences, first-order propagation")


