"""Paper 003 (Billings & Fakhouri 1978): correlation identification of the Hammerstein model
and of the feedforward system (a Hammerstein branch in parallel with a linear path).

The input is u = x + b, x zero-mean white Gaussian with variance eps^2 = mu, b != 0 a mean
level (so that every power of F contributes to the first-order correlation, sec. 2). Primes
denote removed means, x' = u - mean(u), z' = z - mean(z).

Hammerstein, y = H[F(u)] (sec. 2): the first-order cross-correlation is proportional to the
impulse response, phi_xz'(s) = alpha h(s) (eq. 13); a pulse transfer function is fitted to it
(eq. 14) and the polynomial follows by least squares on the raw record (eqs. 15-17).

Feedforward, z = H1[u] + H2[F(u)] (sec. 3):

1. phi_xz'(s) = mu h1(s) + beta h2(s) = h3(s) (eq. 20) and the second-order correlation
   phi_xxz'(s) = kappa h2(s) (eqs. 21-28), which the parallel path cannot reach (eq. 22).
2. Pulse transfer functions fitted to both: kappa H2 of order n to eq. 28; to eq. 20 the
   sum mu H1 + beta (kappa H2 shape), i.e. mu H1 of order n with h2 known up to scale.
3. Eqs. (29)-(30): z = rho H3[u] + sum_t omega_t' kappa H2[u^t] by least squares.
4. Eq. (32): rho h3 + omega_1' kappa h2 = h1 + omega_1 h2, fitted with an n-th order model:
   the parallel path. As the paper notes, the linear term of F cannot be separated from H1,
   so it is reported in the parallel path and F has no u^1 term.

Choices where the paper is silent or that we add; the numbers are medians / scatter over
100 records of the Table 1 example (``reproduce.bf``, input mean 2, variance 4):

* Pulse transfer functions are fitted like step 1 of paper 000's CLS (and Isermann et al.'s
  correlation + LS): the ARX regression of the shared builder with the correlation function
  as "output" and the input's own correlation as "input" (phi_xx for eqs. 13 and 20, the
  autocorrelation of x'^2 - mean, = 2 phi_xx^2 by eq. 25, for eq. 28) over the lags
  -tau_max..tau_max (``DEFAULT_TAU_MAX`` = 35).
* The parallel path (step 4) is reduced to order n by ERA (``hammer_ros.identification.era``) from its
  impulse response: with omega_1 != 0, h1 + omega_1 h2 has order 2n, and ERA's balanced
  truncation keeps the dominant part (output fit 90 % at order 2 on our test system, where
  an ARX fit of the impulse response gives 50 %); with omega_1 = 0 (Table 1) it is exact.
* Step 2 for eq. 20 uses the structure h3 = mu h1 + beta h2 with kappa H2 already known
  (``split_first_order_correlation``) instead of an unstructured order-2n fit, whose
  near-cancelling pole/zero pairs (H1 and H2 have close poles) can come out unstable; eq.
  (29) then takes the column mu H1[u] in place of H3[u] (same span with kappa H2[u]).
* Eqs. (16) and (29) get a constant column (gamma_0, H[1]): the smoothed impulse responses
  never have exactly the right static gain, and without gamma_0 that mismatch leaks into
  the other coefficients (steps 1-4 alone: gamma_3/gamma_4 = 2.56 +- 0.98 without it,
  3.07 +- 0.40 with it; truth 3).
* ``REFINEMENTS`` = 1 repetition (ours, not the paper's): each correlation is recomputed on
  z minus the identified parts that cannot correlate with its regressor in expectation, the
  parallel path for eq. 21 (eq. 22) and the part of the branch input F(u) uncorrelated with
  x, resp. x'^2 (for an i.i.d. input, at every lag). The expected correlations are
  unchanged; their estimation noise, which dominates when one path is strong, is gone:
  H2's d_1 scatter 0.055 -> 0.004, gamma_3/gamma_4 0.45 -> 0.016; for the Hammerstein model
  of paper 000's G1 with u = 1 + N(0, 1) and a cubic F (5000 samples) the pole RSS median
  drops from 0.18 to 0.003. ``refinements=0`` gives the paper's steps alone.
* The gain split between F and the linear block is not identifiable; the identified linear
  block (H, or H2 for the feedforward system) is normalised to unit static gain and F
  carries the gain (as paper 000's G1 and G2 have unit static gain).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, signal

from ..errors import IdentificationError
from .correlation import auto_correlation, centred_square, cross_correlation, second_order_cross_correlation
from .era import eigensystem_realization
from .linear import LinearModel
from .regression import fit_regression, polynomial_basis, solve_least_squares
from .result import IdentificationResult
from .runs import Runs, per_run
from .simulate import simulate_hammerstein, simulate_parallel
from .static_maps import PolynomialMap

DEFAULT_TAU_MAX = 35
REFINEMENTS = 1
STRUCTURES = ("hammerstein", "feedforward")


@dataclass(frozen=True, eq=False)
class HammersteinFit:
    """y = H[F(u)], F ascending from u^0 (paper 003, Fig. 1); ``identify_hammerstein`` returns
    H at unit static gain, ``hammerstein_steps`` the unnormalised chain (alpha H, F')."""

    linear: LinearModel
    nonlinearity: PolynomialMap


@dataclass(frozen=True, eq=False)
class FeedforwardFit:
    """z = H2[F(u)] + H1[u] (paper 003, Fig. 3/4): ``branch`` = H2 (at unit static gain from
    ``identify_feedforward``, kappa H2 from ``feedforward_steps``), ``nonlinearity`` = F
    without a u^1 term, ``parallel_path`` = h1 + omega_1 h2 (eq. 32), ``rho`` of eq. (30)."""

    branch: LinearModel
    nonlinearity: PolynomialMap
    parallel_path: LinearModel
    rho: float

    def simulate(self, u: np.ndarray) -> np.ndarray:
        return simulate_parallel(u, self.nonlinearity, self.branch, self.parallel_path)


def fit_pulse_transfer_function(response: np.ndarray, excitation: np.ndarray, order: int, delay: int) -> LinearModel:
    """B(q^-1)/A(q^-1) of order n, relative degree d, from the ARX regression

        response(k) = -sum_{j=1}^{n} a_j response(k-j) + sum_{i=d}^{n} b_i excitation(k-i)

    solved by least squares (paper 003 eq. 14, "a least squares algorithm", Isermann et al.
    1974) over the lags of two correlation functions, as in paper 000 CLS step 1."""
    reg, theta = fit_regression(response, excitation, order, delay)
    a, b = reg.split(theta)
    numerator = np.zeros(order + 1)
    numerator[reg.input_lags] = b[:, 0]
    return LinearModel(numerator, np.concatenate([[1.0], a]))


def filtered_powers(u: np.ndarray, linear: LinearModel, poly: int, runs: Runs | None = None) -> np.ndarray:
    """The columns H[u^t], t = 0..poly, of eqs. (16) and (29) (with the constant t = 0), each run
    of ``runs`` filtered from rest."""
    return per_run(lambda part: signal.lfilter(linear.b, linear.a, part, axis=0),
                   polynomial_basis(u, poly, constant=True), runs)


def _check(u: np.ndarray, z: np.ndarray, tau_max: int, runs: Runs | None = None) -> tuple[np.ndarray, np.ndarray]:
    u = np.asarray(u, dtype=float).ravel()
    z = np.asarray(z, dtype=float).ravel()
    if u.size != z.size:
        raise IdentificationError(f"input and output differ in length ({u.size} vs {z.size})")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(z))):
        raise IdentificationError("the record holds NaN or infinite samples")
    if np.ptp(u) == 0.0:
        raise IdentificationError("the input is constant: no correlation to identify from")
    if tau_max < 1:
        raise IdentificationError(f"--tau-max: must be >= 1 (got {tau_max})")
    longest, what = (u.size, "the record") if runs is None else (int(runs.lengths.max()), "the longest run")
    if longest < 2 * tau_max + 1:
        raise IdentificationError(f"--tau-max: {tau_max} needs >= {2 * tau_max + 1} samples, {what} has {longest}")
    return u, z


def _unit_static_gain(linear: LinearModel, coefficients: np.ndarray) -> tuple[LinearModel, PolynomialMap]:
    """(H / H(1), H(1) F): the same chain with the linear block at unit static gain (left as
    is when H(1) is zero, e.g. a differentiating block)."""
    gain = linear.dc_gain
    scale = np.sum(np.abs(linear.b)) / np.sum(np.abs(linear.a))
    if not np.isfinite(gain) or abs(gain) <= 1e-9 * scale:
        return linear, PolynomialMap(coefficients)
    # + 0.0 turns the -0.0 of a negative gain into 0.0
    return LinearModel(linear.b / gain + 0.0, linear.a), PolynomialMap(np.asarray(coefficients) * gain + 0.0)


def _response_length(*models: LinearModel) -> int:
    """Markov parameters handed to ERA: until the slowest pole of the models has decayed to
    1e-6, at least 50 and at most 300 (the Hankel matrix of a smoothed, exactly finite-order
    response has its rank from a short stretch already)."""
    radius = max(float(np.max(np.abs(m.poles), initial=0.0)) for m in models)
    if not 0.0 < radius < 1.0:
        return 50 if radius <= 0.0 else 300
    return int(np.clip(np.ceil(np.log(1e-6) / np.log(radius)), 50, 300))


def uncorrelated_part(f: np.ndarray, regressor: np.ndarray) -> np.ndarray:
    """f minus its least-squares projection on [1, regressor]: for an i.i.d. input, the part of
    f(u(k)) that has no correlation with regressor(k - s) at any lag s."""
    basis = np.column_stack([np.ones_like(regressor), regressor])
    return f - basis @ solve_least_squares(basis, f)


def hammerstein_steps(u: np.ndarray, z: np.ndarray, correlated: np.ndarray, order: int, delay: int, poly: int,
                      tau_max: int, runs: Runs | None = None) -> HammersteinFit:
    """Paper 003 sec. 2 on a checked record, with phi_xz' computed on ``correlated`` (z, or
    its refinement): phi_xz'(s) = alpha h(s) (eqs. 6-13), Z{alpha h} fitted to it (eq. 14),
    then gamma_t' of

        z(i) = sum_t gamma_t' sum_j alpha h(j) u^t(i-j) + e(i)            (eqs. 15-16)

    by least squares (eq. 17), t = 0..poly (t = 0: the constant, see the module notes).
    Returns the chain (alpha H, F') before normalisation. ``runs``: no correlation product
    crosses a run's boundary, H[u^t] starts from rest in every run (the means stay the record's)."""
    x = u - u.mean()
    phi_xz = cross_correlation(x, correlated - correlated.mean(), tau_max, runs)
    alpha_h = fit_pulse_transfer_function(phi_xz, auto_correlation(x, tau_max, runs), order, delay)
    return HammersteinFit(alpha_h, PolynomialMap(solve_least_squares(filtered_powers(u, alpha_h, poly, runs), z)))


def identify_hammerstein(
    u: np.ndarray,
    z: np.ndarray,
    order: int,
    delay: int,
    poly: int,
    tau_max: int = DEFAULT_TAU_MAX,
    refinements: int = REFINEMENTS,
    runs: Runs | None = None,
) -> HammersteinFit:
    """The Hammerstein model of paper 003 sec. 2 (``hammerstein_steps``); each refinement
    recomputes phi_xz' on z - alpha H[r], r = the part of F'(u) uncorrelated with x (module
    notes). The result has H at unit static gain. ``runs``: ``hammerstein_steps``; the refinement
    simulates every run from rest."""
    u, z = _check(u, z, tau_max, runs)
    x = u - u.mean()
    fit = hammerstein_steps(u, z, z, order, delay, poly, tau_max, runs)
    for _ in range(refinements):
        correlated = z - per_run(fit.linear.simulate, uncorrelated_part(fit.nonlinearity(u), x), runs)
        fit = hammerstein_steps(u, z, correlated, order, delay, poly, tau_max, runs)
    return HammersteinFit(*_unit_static_gain(fit.linear, fit.nonlinearity.coefficients))


def split_first_order_correlation(
    phi_xz: np.ndarray, phi_xx: np.ndarray, kappa_h2: LinearModel, order: int
) -> LinearModel:
    """mu H1 (order n, input lags 0..n) from phi_xz' = mu h1 + beta h2 (eq. 20), with h2 known
    up to scale from eq. 28: with s = kappa H2 phi_xx,

        A1(q) (phi_xz' - beta' s)(k) = B1(q) phi_xx(k) + e(k),

    an ARX regression for each beta', and beta' minimises its residual (variable projection,
    Brent's method). It starts from the linear fit in which beta' A1(q) is relaxed to a free
    polynomial (a second input channel); that relaxation alone lets B1/A1 absorb part of h2
    whenever the model order exceeds H1's, hence the exact constraint."""
    s = kappa_h2.simulate(phi_xx)
    reg, theta = fit_regression(phi_xz, np.column_stack([phi_xx, s]), order, 0)
    relaxed_beta = float(reg.split(theta)[1][0, 1])

    def fit(beta: float):
        return fit_regression(phi_xz - beta * s, phi_xx, order, 0)

    def residual(beta: float) -> float:
        reg, theta = fit(beta)
        return float(np.sum((reg.target - reg.phi @ theta) ** 2))

    start = relaxed_beta if relaxed_beta != 0.0 else 1.0
    search = optimize.minimize_scalar(residual, bracket=(start, 1.05 * start))
    beta = float(search.x) if search.success and np.isfinite(search.x) else relaxed_beta
    reg, theta = fit(beta)
    a, b = reg.split(theta)
    return LinearModel(b[:, 0], np.concatenate([[1.0], a]))


def feedforward_least_squares(
    u: np.ndarray, z: np.ndarray, mu_h1: LinearModel, kappa_h2: LinearModel, poly: int, runs: Runs | None = None
) -> tuple[float, np.ndarray]:
    """Eqs. (29)-(30): (rho, omega_0'..omega_poly') minimising ||z - rho H3[u] - sum_t omega_t'
    kappa H2[u^t]||. The beta h2 part of h3 = mu h1 + beta h2 lies in the span of the column
    kappa H2[u], so the column mu H1[u] gives the same fit, with omega_1' then holding
    omega_1' + rho beta / kappa (eq. 31)."""
    columns = np.column_stack([per_run(mu_h1.simulate, u, runs), filtered_powers(u, kappa_h2, poly, runs)])
    theta = solve_least_squares(columns, z)
    return float(theta[0]), theta[1:]


def feedforward_steps(u: np.ndarray, z: np.ndarray, first: np.ndarray, second: np.ndarray, order: int, delay: int,
                      poly: int, tau_max: int, runs: Runs | None = None) -> FeedforwardFit:
    """Paper 003 sec. 3, steps 1-4, on a checked record, with the first-order correlation
    (eq. 19) computed on ``first`` and the second-order one (eq. 21) on ``second`` (both z,
    or their refinements):

    1-2. kappa H2 (order n, delay d) fitted to phi_xxz' = kappa h2 (eq. 28); mu H1 split off
         phi_xz' = mu h1 + beta h2 (eq. 20, ``split_first_order_correlation``);
    3.   rho, omega' by eqs. (29)-(30);
    4.   the parallel path (order n, delay d): the ERA realisation of the impulse response
         rho mu h1 + omega_1' kappa h2 = h1 + omega_1 h2 (eq. 32).

    Returns the branch as (kappa H2, F' = omega' with omega_1' = 0) before normalisation."""
    x = u - u.mean()
    phi_xxz = second_order_cross_correlation(u, second, tau_max, runs)
    kappa_h2 = fit_pulse_transfer_function(phi_xxz, auto_correlation(centred_square(u), tau_max, runs), order, delay)
    phi_xz = cross_correlation(x, first - first.mean(), tau_max, runs)
    mu_h1 = split_first_order_correlation(phi_xz, auto_correlation(x, tau_max, runs), kappa_h2, order)
    rho, omega = feedforward_least_squares(u, z, mu_h1, kappa_h2, poly, runs)
    length = _response_length(mu_h1, kappa_h2)
    combined = rho * mu_h1.markov_parameters(length) + omega[1] * kappa_h2.markov_parameters(length)
    branch_input = PolynomialMap(np.concatenate([omega[:1], [0.0], omega[2:]]))
    parallel_path = eigensystem_realization(combined, order).to_linear_model(delay)
    return FeedforwardFit(kappa_h2, branch_input, parallel_path, rho)


def identify_feedforward(
    u: np.ndarray,
    z: np.ndarray,
    order: int,
    delay: int,
    poly: int,
    tau_max: int = DEFAULT_TAU_MAX,
    refinements: int = REFINEMENTS,
    runs: Runs | None = None,
) -> FeedforwardFit:
    """The feedforward system of paper 003 sec. 3 (``feedforward_steps``), z = H1[u] + H2[F(u)],
    H1 and H2 of order ``order`` and relative degree ``delay``, F of degree ``poly`` >= 2.

    Each refinement recomputes the first-order correlation on z - kappa H2[r_x] and the
    second-order one on z - H1_hat[u] - kappa H2[r_w], r_x and r_w the parts of the branch
    input F'(u) uncorrelated with x and with x'^2 (module notes). The result has H2 at unit
    static gain. ``runs``: as in ``identify_hammerstein``."""
    if poly < 2:
        raise IdentificationError(f"--poly: the feedforward system needs a polynomial of degree >= 2 (got {poly}); "
                                  "with a linear F it is a linear system")
    u, z = _check(u, z, tau_max, runs)
    x, w = u - u.mean(), centred_square(u)
    fit = feedforward_steps(u, z, z, z, order, delay, poly, tau_max, runs)
    for _ in range(refinements):
        branch_input = fit.nonlinearity(u)
        first = z - per_run(fit.branch.simulate, uncorrelated_part(branch_input, x), runs)
        second = (z - per_run(fit.parallel_path.simulate, u, runs)
                  - per_run(fit.branch.simulate, uncorrelated_part(branch_input, w), runs))
        fit = feedforward_steps(u, z, first, second, order, delay, poly, tau_max, runs)
    branch, nonlinearity = _unit_static_gain(fit.branch, fit.nonlinearity.coefficients)
    return FeedforwardFit(branch, nonlinearity, fit.parallel_path, fit.rho)


def _model_json(linear: LinearModel) -> dict:
    return {
        "a": linear.a[1:].tolist(),
        "b": linear.b.tolist(),
        "poles": [[float(p.real), float(p.imag)] for p in linear.poles],
        "zeros": [[float(q.real), float(q.imag)] for q in linear.zeros],
    }


def identify_bf(v: np.ndarray, y: np.ndarray, options, structure: str = "hammerstein") -> IdentificationResult:
    """``bf-hammerstein`` / ``bf-feedforward``: ``identify_hammerstein`` or
    ``identify_feedforward`` with the options' order, delay, poly and tau_max (default
    ``DEFAULT_TAU_MAX``). The result's linear block is H (H2, the Hammerstein branch, for the
    feedforward system), at unit static gain; the feedforward system's parallel path is in
    the JSON as ``parallel_path`` {a, b, poles, zeros}; ``simulate`` runs the whole model."""
    if structure not in STRUCTURES:
        raise IdentificationError(f"structure must be one of {STRUCTURES}, got {structure!r}")
    tau_max = DEFAULT_TAU_MAX if options.tau_max is None else int(options.tau_max)
    extra: dict = {"tau_max": tau_max}
    if structure == "hammerstein":
        fit = identify_hammerstein(v, y, options.order, options.delay, options.poly, tau_max, runs=options.runs)
        linear, nonlinearity = fit.linear, fit.nonlinearity

        def simulate(u: np.ndarray) -> np.ndarray:
            return simulate_hammerstein(u, nonlinearity, linear)
    else:
        fit = identify_feedforward(v, y, options.order, options.delay, options.poly, tau_max, runs=options.runs)
        linear, nonlinearity, simulate = fit.branch, fit.nonlinearity, fit.simulate
        extra["parallel_path"] = _model_json(fit.parallel_path)
    return IdentificationResult(
        method=f"bf-{structure}", linear=linear, simulate=simulate, order=options.order,
        nonlinearity=nonlinearity, extra=extra,
    )
