"""Semiparametric Hammerstein identification: D'Amato, Mitchell, Teixeira & Bernstein, paper 002.

Two records, two steps (paper 002, secs. III-IV). Notation of the paper: u is the input,
v = H(u) the inaccessible intermediate signal, y = G(z) v the output.

1. A sufficiently rich record (u, y) gives the linear block G_hat (sec. III). The paper uses
   retrospective cost optimisation (RCO) and, in Example 6.3, an output-error model (eq. 21);
   we fit the output-error model with ``scipy.optimize.least_squares``, initialised from the
   ARX least-squares estimate on the shared regression builder. The nonlinearity is ignored
   in this step (sec. III: "we assume that H is approximately linear"): for an i.i.d. input,
   H(u) = c u + w with w uncorrelated with u (Bussgang), so the fit returns c G; c is the
   unidentifiable scale lambda of Fig. 1b.
2. A single-harmonic record u = A_0 sin(Omega_0 k) (eq. 5) in harmonic steady state gives
   v_hat by l-delay input reconstruction (eq. 8), the nonharmonic phase shift of v_hat
   relative to u by the symmetry search (eqs. 9-12, sec. IV-D) and the nonparametric map
   H_hat = {(u(k), v_tilde(k))} (eqs. 13-14).

Readings and additions where the paper is silent or ambiguous (each repeated where it is
implemented):

- The harmonic steady state is periodic with period N_0 (samples), so it is folded onto one
  period (the mean over the whole periods after the settling time of G_hat). Eq. (8) is
  evaluated on this periodic signal harmonic by harmonic; output noise is handled by keeping
  only the harmonics that stand out of the period-to-period scatter.
- The paper requires Omega_0 = pi / (2m), N_0 = 4m, so that the symmetry points fall on
  samples (sec. IV-B). We accept any whole number N_0 >= 8 of samples per period: delta (of
  u) is searched on the half-sample grid and epsilon = delta + q with q = d - l an integer.
- The symmetry search runs on the folded signal, where the windowed sums (9) and (10) become
  one circular sum over all mirror pairs of the period.
- The estimated map is symmetrised: u and v = H(u) share the symmetry points (sec. IV-B), so
  the two samples mirrored about the found centre are averaged.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import signal
from scipy.optimize import least_squares, minimize_scalar

from ..errors import IdentificationError
from .linear import LinearModel
from .methods import IdentifyOptions
from .regression import build_regression, delayed, solve_least_squares
from .result import IdentificationResult
from .runs import Runs, per_run, several
from .static_maps import NonparametricMap

SETTLING_TOLERANCE = 1e-4  # transients decay to this fraction before the steady state is used
HARMONIC_SIGNIFICANCE = 4.0  # keep a harmonic when |mean| > this many standard errors
SINE_VARIANCE_FRACTION = 0.9  # the harmonic input must be at least this much one sine
EVEN_TOLERANCE = 0.1  # normalised symmetry error under which the quarter-period centre counts
STATIC_GAIN_FLOOR = 1e-2  # |G(1)| below this fraction of the peak gain: offset not identifiable
EXPLAINED_VARIANCE_FACTOR = 10.0  # the linear fit must explain 10 x what p parameters fit to noise


# --------------------------------------------------------------------------- linear block (sec. III)


def settling_samples(model: LinearModel, tolerance: float = SETTLING_TOLERANCE) -> int | None:
    """Samples until the slowest mode rho^k of ``model`` has decayed to ``tolerance``
    (None when the model is not asymptotically stable)."""
    rho = float(np.max(np.abs(model.poles))) if model.order else 0.0
    if rho >= 1.0:
        return None
    if rho < tolerance:
        return 1
    return int(np.ceil(np.log(tolerance) / np.log(rho)))


@dataclass(frozen=True, eq=False)
class OutputErrorFit:
    """The output-error estimate of sec. III / eq. (21) and how much of y it explains."""

    model: LinearModel
    explained_variance: float  # 1 - SSE / SST on the fitted (mean-removed) samples
    samples: int
    parameters: int


def fit_output_error(u: np.ndarray, y: np.ndarray, order: int, delay: int, runs: Runs | None = None) -> OutputErrorFit:
    """Output-error model y(k) = B(q^-1)/F(q^-1) u(k) + c + e(k) (paper 002, eq. 21, Example
    6.3), the alternative the paper names to RCO for the linear block (sec. III).

    F has degree ``order``, B holds the lags delay..order (the shared ARX lag set,
    ``markov_lags(order, delay)``); u enters without its mean and the constant c takes the
    output offset (an offset of H only shifts y). The ARX least-squares estimate
    (``build_regression``, on mean-free data) starts a Levenberg-Marquardt search on
    sum e(k)^2 with the analytic gradient de/db_i = -q^-i u/F, de/df_j = q^-j y_hat/F,
    de/dc = -1. The initial state is not assumed zero (sec. III): the residuals of the first
    settling time of the ARX estimate are left out of the cost.

    ``runs`` (several experiments laid end to end): the ARX start on rows within the runs, every
    run simulated from rest and its own first settling time left out.
    """
    u0 = np.asarray(u, float) - np.mean(u)
    y = np.asarray(y, float)
    runs = several(runs)
    regression = build_regression(y - np.mean(y), u0, order, delay, runs=runs)
    a_arx, b_arx = regression.split(solve_least_squares(regression.phi, regression.target))
    lags = regression.input_lags
    p0 = np.concatenate([a_arx, b_arx[:, 0], [np.mean(y)]])
    start = settling_samples(_model(p0, order, lags))
    shortest = u0.size if runs is None else int(runs.lengths.min())
    burn_in = min(start or shortest // 4, shortest // 4)
    used = slice(burn_in, None) if runs is None else runs.rows(burn_in)  # the samples in the cost

    def simulate(p):
        model = _model(p, order, lags)
        return model, per_run(model.simulate, u0, runs)

    def residuals(p):
        return (y - p[-1] - simulate(p)[1])[used]

    def jacobian(p):
        model, y_hat = simulate(p)
        u_f = per_run(lambda part: signal.lfilter([1.0], model.a, part), u0, runs)
        y_f = per_run(lambda part: signal.lfilter([1.0], model.a, part), y_hat, runs)
        columns = ([per_run(lambda part, j=j: delayed(part, j), y_f, runs) for j in range(1, order + 1)]
                   + [-per_run(lambda part, i=i: delayed(part, i), u_f, runs) for i in lags])
        return np.column_stack([*columns, -np.ones(u0.size)])[used]

    with np.errstate(over="ignore", invalid="ignore"):
        solution = least_squares(residuals, p0, jac=jacobian, method="lm", x_scale="jac")
    model = _model(solution.x, order, lags)
    if not (np.all(np.isfinite(solution.x)) and model.is_stable()):
        raise IdentificationError(
            "DATA: the output-error fit of the linear block is unstable; try another --order or a longer record"
        )
    sse = float(np.sum(solution.fun**2))
    sst = float(np.sum((y[used] - np.mean(y[used])) ** 2))
    explained = 1.0 - sse / sst if sst > 0 else 0.0
    return OutputErrorFit(model, explained, solution.fun.size, p0.size)


def _model(p: np.ndarray, order: int, lags: np.ndarray) -> LinearModel:
    b = np.zeros(order + 1)
    b[lags] = p[order : order + lags.size]
    return LinearModel(b, np.concatenate([[1.0], p[:order]]))


def minimum_phase_counterpart(model: LinearModel, delay: int, omega_ref: float = 0.0) -> LinearModel:
    """The stable approximate inverse used for eq. (8) when G_hat is non-minimum-phase.

    With G_hat = q^-l B(q^-1)/A(q^-1) (l = ``delay``, the relative degree the model was fitted
    with), every zero z_i of B outside the unit circle is reflected to 1/conj(z_i) with the
    gain |z_i| (same magnitude on the unit circle, (1 - z_i q^-1) -> |z_i| (1 - q^-1/conj(z_i))),
    and leading zero coefficients of B (zeros at infinity) are dropped. The returned model
    q^-l B_mp/A has the magnitude response of G_hat and a stable causal inverse; its sign is
    fixed so that G_hat/G_mp has a positive real part at ``omega_ref`` (the harmonic's frequency).

    G_hat/G_mp is all-pass. Near omega = 0 it is close to a pure delay: a model fitted with l
    below the true relative degree d has d - l leading coefficients that are ~0, i.e. d - l
    zeros far outside the unit circle, each reflected to ~0, i.e. one unit delay each. The
    reconstruction is then v(k - (d - l)), the shift q = d - l that the symmetry search finds
    (paper 002, sec. IV-B).
    """
    b = model.b[delay:] if model.b.size > delay else np.zeros(1)
    nonzero = np.flatnonzero(b)
    if nonzero.size == 0:
        raise IdentificationError("DATA: the linear block estimate has a zero numerator")
    b = b[nonzero[0] :]
    zeros = np.roots(b).astype(complex) if b.size > 1 else np.zeros(0, complex)
    outside = np.abs(zeros) > 1.0
    gain = b[0] * np.prod(np.abs(zeros[outside]))
    reflected = np.where(outside, 1.0 / np.conj(zeros), zeros)
    b_mp = gain * np.real(np.poly(reflected))
    minimum_phase = LinearModel(np.concatenate([np.zeros(delay), b_mp]), model.a)
    ratio = _response(model, omega_ref) / _response(minimum_phase, omega_ref)
    return minimum_phase if ratio.real >= 0 else minimum_phase.scaled(-1.0)


def _response(model: LinearModel, omega) -> np.ndarray:
    """G(e^{j omega}) at the frequencies ``omega`` (rad/sample)."""
    return signal.freqz(model.b, model.a, worN=np.atleast_1d(np.asarray(omega, float)))[1]


# --------------------------------------------------------------------------- harmonic steady state


def harmonic_period(u: np.ndarray) -> int:
    """N_0 = 2 pi / Omega_0 of the single-harmonic input (eq. 5), in whole samples.

    Omega_0 minimises the residual of the least-squares fit of a sin + b cos + c (the
    maximum-likelihood frequency; the plain periodogram peak is biased for a few periods),
    searched around the peak of the zero-padded FFT. Raises IdentificationError when u is not
    mostly one sine or its period is not a whole number of samples (the folding of the steady
    state needs N_0 integer; the paper requires Omega_0 = pi/(2m), sec. IV-B)."""
    u = np.asarray(u, float)
    n = u.size
    k = np.arange(n)
    if n < 8 or np.ptp(u) == 0:
        raise IdentificationError("--harmonic: the input is constant or too short to be a sine")

    def residual(omega):
        basis = np.column_stack([np.sin(omega * k), np.cos(omega * k), np.ones(n)])
        return float(np.sum((u - basis @ solve_least_squares(basis, u)) ** 2))

    spectrum = np.abs(np.fft.rfft(u - u.mean(), 8 * n))
    peak = int(np.argmax(spectrum[1:])) + 1
    step = 2 * np.pi / (8 * n)
    bounds = (max(peak - 4, 0.5) * step, (peak + 4) * step)
    omega = minimize_scalar(residual, bounds=bounds, method="bounded", options={"xatol": 1e-6 * step}).x
    fraction = 1.0 - residual(omega) / np.sum((u - u.mean()) ** 2)
    if fraction < SINE_VARIANCE_FRACTION:
        raise IdentificationError(
            f"--harmonic: the input is not a single sine (its fundamental holds {100 * fraction:.0f} % of the variance)"
        )
    period = 2 * np.pi / omega
    whole = int(round(period))
    if whole < 8 or abs(period - whole) * n / period > 0.5:
        raise IdentificationError(
            f"--harmonic: the sine's period is {period:.3f} samples; choose a frequency with a whole number "
            "(>= 8) of samples per period (paper 002 uses Omega_0 = pi/(2m))"
        )
    return whole


@dataclass(frozen=True, eq=False)
class HarmonicSteadyState:
    """The harmonic record folded onto its period: ``u`` (N_0,) is the input averaged over
    the ``y_periods.shape[0]`` whole periods used, ``y_periods`` (P, N_0) the output, one
    row per period, and ``start`` the first sample used."""

    u: np.ndarray
    y_periods: np.ndarray
    start: int

    @property
    def period(self) -> int:
        return self.u.size


def fold_harmonic_record(u: np.ndarray, y: np.ndarray, period: int, settle: int) -> HarmonicSteadyState:
    """The last whole periods of (u, y) after ``settle`` samples (sec. IV: the output is
    measured "once the trajectory of the system reaches steady state")."""
    u = np.asarray(u, float)
    y = np.asarray(y, float)
    periods = (u.size - settle) // period
    if periods < 1:
        raise IdentificationError(
            f"--harmonic: too short: need the settling time ({settle} samples) plus one period "
            f"({period} samples), got {u.size}"
        )
    start = u.size - periods * period
    return HarmonicSteadyState(
        u[start:].reshape(periods, period).mean(axis=0), y[start:].reshape(periods, period), start
    )


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """v_hat over one period (eq. 8) and what was kept of it."""

    v: np.ndarray
    harmonics: int  # harmonics of Omega_0 kept (including the fundamental)
    offset_identified: bool  # False when G_hat(1) ~ 0: the mean of v_hat is set to 0


def reconstruct_intermediate(steady: HarmonicSteadyState, model: LinearModel, delay: int) -> Reconstruction:
    """l-delay input reconstruction, paper 002 eq. (8): v_hat_l(k) = G_hat^-1(z) z^-l y(k) and
    v_hat(k) = v_hat_l(k + l), here in harmonic steady state.

    On the periodic steady state the causal filter z^-l G_mp^-1 (``minimum_phase_counterpart``,
    the stable approximate inverse; the exact inverse of G_hat where G_hat is minimum phase)
    acts on each harmonic h Omega_0 by the factor 1/G_mp(e^{j h Omega_0}), and the advance
    by l cancels z^-l; so V_hat(h) = Y(h) / G_mp(e^{j h Omega_0}) with Y(h) the DFT of the
    folded output. Noise: with P >= 2 periods, a harmonic is kept only when its mean exceeds
    HARMONIC_SIGNIFICANCE standard errors of its period-to-period scatter (the others are
    set to zero instead of being amplified by 1/G_mp). The mean of v_hat is kept only when
    |G_mp(1)| >= STATIC_GAIN_FLOOR x the peak gain over the harmonics (else G_hat cannot
    carry an offset of H to the output, e.g. a series RLC circuit, Example 6.1).
    """
    n0 = steady.period
    spectra = np.fft.rfft(steady.y_periods, axis=1)
    mean = spectra.mean(axis=0)
    periods = spectra.shape[0]
    keep = np.ones(mean.size, bool)
    if periods >= 2:
        scatter = np.sqrt(np.sum(np.abs(spectra - mean) ** 2, axis=0) / (periods * (periods - 1)))
        keep = np.abs(mean) > HARMONIC_SIGNIFICANCE * scatter
    omega = 2 * np.pi * np.arange(mean.size) / n0
    minimum_phase = minimum_phase_counterpart(model, delay, omega[1])
    response = _response(minimum_phase, omega)
    offset_identified = bool(abs(response[0]) >= STATIC_GAIN_FLOOR * np.max(np.abs(response)))
    keep[0] &= offset_identified
    v_hat = np.where(keep, mean / np.where(keep, response, 1.0), 0.0)
    return Reconstruction(np.fft.irfft(v_hat, n0), int(np.count_nonzero(keep[1:])), offset_identified)


# --------------------------------------------------------------------------- symmetry search (sec. IV-C)


def symmetry_error(x: np.ndarray, chunk: int = 32) -> np.ndarray:
    """Symmetry error index beta (paper 002, eqs. 9-10) of one period x(0..N_0-1) of a
    periodic signal, for every candidate centre c = s/2, s = 0..N_0-1 (half-sample grid,
    c in [0, N_0/2)):

        beta(s) = sum_{i=0}^{N_0-1} |x(i) - x((s - i) mod N_0)| / (2 sum_i |x(i) - mean x|).

    On a periodic signal, mirror symmetry about c is symmetry about c + N_0/2 as well, so
    this single circular sum holds the pairs of both windows of eqs. (9) and (10) (symmetric
    about k + N_0/4 and k + 3N_0/4 for the window starting at k = c - N_0/4); beta is
    normalised to 0 for an exactly symmetric and 1 for an antisymmetric signal.
    """
    x = np.asarray(x, float)
    n0 = x.size
    # row t of the windows is x((N_0 - 1 - t - i) mod N_0), i = 0..N_0-1: the mirror of x about s = N_0 - 1 - t
    mirrored = sliding_window_view(np.concatenate([x[::-1], x[::-1]]), n0)
    beta = np.empty(n0)
    for first in range(0, n0, chunk):
        s = np.arange(first, min(first + chunk, n0))
        beta[s] = np.sum(np.abs(x[None, :] - mirrored[(n0 - 1 - s) % n0]), axis=1)
    spread = 2.0 * np.sum(np.abs(x - x.mean()))
    return beta / spread if spread > 0 else beta


@dataclass(frozen=True, eq=False)
class PhaseShift:
    """The nonharmonic phase shift of v_hat relative to u (sec. IV-D).

    ``delay`` q = epsilon - delta in samples (= d - l, the relative-degree error of G_hat;
    phi_hat = Omega_0 q); ``alternative`` the runner-up candidate (q -+ N_0/2, or -+ N_0/4 for
    an even nonlinearity); ``centre_doubled`` 2 epsilon (epsilon mod N_0/2); ``symmetry_error``
    beta at epsilon; ``even`` whether the centre a quarter period away is as symmetric (eq. 12).
    """

    delay: float
    alternative: float
    centre_doubled: int
    symmetry_error: float
    even: bool

    def runner_up(self, period: int) -> PhaseShift:
        """The other candidate of sec. IV-D as a PhaseShift (its centre moved with it)."""
        centre = int(round(self.centre_doubled + 2 * (self.alternative - self.delay))) % period
        return replace(self, delay=self.alternative, alternative=self.delay, centre_doubled=centre)


def nonharmonic_phase_shift(u: np.ndarray, v_hat: np.ndarray) -> PhaseShift:
    """Symmetry search (paper 002, sec. IV-C, eqs. 9-12) on one period of u and of v_hat.

    delta minimises beta of u on the half-sample grid (eq. 11; the paper's delta "known from
    the harmonic input"). q = d - l is an integer (sec. IV-B), so epsilon = delta + q is
    searched over whole samples q. Candidates (sec. IV-D): beta has period N_0/2, so q is
    known modulo N_0/2 (phi_hat and phi_hat + pi); when beta also vanishes a quarter period
    away from epsilon (eq. 12, an even nonlinearity) q is known modulo N_0/4 only. As the
    paper argues, q is small compared with N_0, so q is taken in (-N_0/4, N_0/4], or in
    (-N_0/8, N_0/8] for an even nonlinearity; the other candidate is kept in ``alternative``
    (for an even nonlinearity it gives the erroneous map of Fig. 8b).
    """
    n0 = u.size
    s_u = int(np.argmin(symmetry_error(u)))
    beta_v = symmetry_error(v_hat)
    q = np.arange(-((n0 - 1) // 4), n0 // 4 + 1)
    errors = beta_v[(s_u + 2 * q) % n0]
    best = int(q[np.argmin(errors)])
    quarter = beta_v[(s_u + 2 * best + n0 // 2) % n0]
    even = bool(quarter <= EVEN_TOLERANCE)
    if even:
        inside = np.abs(q) <= n0 / 8
        best = int(q[inside][np.argmin(errors[inside])])
    step = n0 / (4 if even else 2)
    alternative = best - step if best > 0 else best + step
    centre = (s_u + 2 * best) % n0
    return PhaseShift(float(best), alternative, centre, float(beta_v[centre]), even)


# --------------------------------------------------------------------------- nonparametric map (sec. IV-D)


def nonparametric_map(u: np.ndarray, v_hat: np.ndarray, shift: PhaseShift) -> NonparametricMap:
    """H_hat = {(u(k), v_tilde(k))} with v_tilde(k) = v_hat(k + q) (paper 002, eqs. 13-14).

    Pairing u(k) with v_hat(k + q) is pairing u(k - q) with v_hat(k); u is shifted (by a
    circular Fourier shift when q is a half sample: exact for the band-limited sine, where
    shifting v_hat would ring at its corners). The two samples mirrored about epsilon hold
    the same point of H (u and v = H(u) share the symmetry centres, sec. IV-B) and are
    averaged, which also cancels the part of a phase error of G_hat that is odd about
    epsilon. The map is the half period from epsilon to epsilon + N_0/2 (u sweeps its range
    once).
    """
    n0 = u.size
    u_shifted = _circular_shift(u, shift.delay)
    k = np.arange(n0)
    mirror = (shift.centre_doubled - k) % n0
    u_sym = 0.5 * (u_shifted + u_shifted[mirror])
    v_sym = 0.5 * (v_hat + v_hat[mirror])
    half = (2 * k - shift.centre_doubled) % (2 * n0) <= n0
    return NonparametricMap(u_sym[half], v_sym[half])


def _circular_shift(x: np.ndarray, delay: float) -> np.ndarray:
    """x(k - delay) for a periodic x; a Fourier shift when ``delay`` is not an integer."""
    if float(delay).is_integer():
        return np.roll(x, int(delay))
    h = np.fft.rfftfreq(x.size) * 2 * np.pi
    return np.fft.irfft(np.fft.rfft(x) * np.exp(-1j * h * delay), x.size)


def map_error(estimate, truth, low: float, high: float, points: int = 401) -> float:
    """Normalised RMS error of an estimated map after removing the unidentifiable scale and
    offset (paper 002, Fig. 1b): min_{a, b} ||H - (a H_hat + b)|| / ||H - mean H|| on a uniform
    grid over [low, high]."""
    grid = np.linspace(low, high, points)
    h = np.asarray(truth(grid), float)
    basis = np.column_stack([np.asarray(estimate(grid), float), np.ones(points)])
    residual = h - basis @ solve_least_squares(basis, h)
    return float(np.linalg.norm(residual) / np.linalg.norm(h - h.mean()))


# --------------------------------------------------------------------------- the method


@dataclass(frozen=True, eq=False)
class SemiparametricEstimate:
    """Every step of the method: the linear fit (sec. III), the folded harmonic steady state,
    v_hat (eq. 8), the nonharmonic phase shift (sec. IV-C/D) and H_hat (eqs. 13-14)."""

    fit: OutputErrorFit
    steady: HarmonicSteadyState
    reconstruction: Reconstruction
    shift: PhaseShift
    nonlinearity: NonparametricMap

    def alternative_nonlinearity(self) -> NonparametricMap:
        """H_hat for the runner-up phase shift (for an even H: the black circles of Fig. 8b)."""
        return nonparametric_map(
            self.steady.u, self.reconstruction.v, self.shift.runner_up(self.steady.period)
        )


def semiparametric(
    u: np.ndarray, y: np.ndarray, u_harmonic: np.ndarray, y_harmonic: np.ndarray, order: int, delay: int,
    runs: Runs | None = None,
) -> SemiparametricEstimate:
    """Paper 002, both steps: G_hat of the given order and relative degree l = ``delay`` from
    the rich record (u, y) (of ``runs``, ``fit_output_error``), then H_hat from the single-harmonic record."""
    u_harmonic, y_harmonic = np.asarray(u_harmonic, float), np.asarray(y_harmonic, float)
    if u_harmonic.shape != y_harmonic.shape or u_harmonic.ndim != 1:
        raise IdentificationError("--harmonic: input and output must be 1-D and of equal length")
    if np.size(u) <= 4 * order + 2:
        raise IdentificationError(f"DATA: {np.size(u)} samples are too few for --order {order}")
    fit = fit_output_error(u, y, order, delay, runs)
    if fit.explained_variance < EXPLAINED_VARIANCE_FACTOR * fit.parameters / fit.samples:
        raise IdentificationError(
            f"DATA: the linear block explains only {100 * fit.explained_variance:.2f} % of y (y is nearly "
            "uncorrelated with the input: an even nonlinearity needs a rich input with a non-zero mean)"
        )
    period = harmonic_period(u_harmonic)
    steady = fold_harmonic_record(u_harmonic, y_harmonic, period, settling_samples(fit.model) or 0)
    reconstruction = reconstruct_intermediate(steady, fit.model, delay)
    shift = nonharmonic_phase_shift(steady.u, reconstruction.v)
    return SemiparametricEstimate(
        fit, steady, reconstruction, shift, nonparametric_map(steady.u, reconstruction.v, shift)
    )


def identify_semiparametric(v: np.ndarray, y: np.ndarray, options: IdentifyOptions) -> IdentificationResult:
    """Semiparametric identification (paper 002) as an ``identify`` method: G_hat from the
    rich record (v, y) (``v`` is the system input, paper 002's u), H_hat from the
    single-harmonic record ``options.harmonic = (u2, y2)`` (``--harmonic``).

    ``options.order`` and ``options.delay`` (= l, the relative degree assumed for G_hat) set
    the output-error model. The nonlinearity is returned in the units in which G_hat takes
    its input (lambda = 1/c, c the gain the linear fit absorbed from H), so G_hat H_hat(u)
    reproduces y. ``extra`` (top-level keys of the JSON document):

    - ``delay_found`` q = d - l and ``relative_degree`` l + q, the estimate of d;
    - ``phase_shift`` phi_hat = Omega_0 q (rad); ``delay_candidates`` [q, runner-up];
    - ``even_nonlinearity``: True when H looks even, so that the runner-up is only N_0/4 away
      and gives a different map (Fig. 8b); the returned map assumes |q| < N_0/8 and the
      runner-up's map is added as ``alternative_nonlinearity``;
    - ``symmetry_error`` beta at epsilon (0: v_tilde exactly as symmetric as u), ``period``
      N_0, ``periods`` used, ``harmonics`` kept, ``offset_identified`` (False: the map has zero
      mean over the period) and ``linear_explained_variance`` of the output-error fit.
    """
    if options.harmonic is None:
        raise IdentificationError("--harmonic: the semiparametric method needs the single-harmonic record")
    estimate = semiparametric(v, y, *options.harmonic, options.order, options.delay, options.runs)
    model, nonlinearity, shift = estimate.fit.model, estimate.nonlinearity, estimate.shift
    period = estimate.steady.period
    extra = {
        "delay_found": _number(shift.delay),
        "relative_degree": _number(options.delay + shift.delay),
        "phase_shift": float(2 * np.pi * shift.delay / period),
        "delay_candidates": [_number(shift.delay), _number(shift.alternative)],
        "even_nonlinearity": shift.even,
        "symmetry_error": shift.symmetry_error,
        "period": period,
        "periods": int(estimate.steady.y_periods.shape[0]),
        "harmonics": estimate.reconstruction.harmonics,
        "offset_identified": estimate.reconstruction.offset_identified,
        "linear_explained_variance": estimate.fit.explained_variance,
    }
    if shift.even:
        extra["alternative_nonlinearity"] = estimate.alternative_nonlinearity().to_json()
    return IdentificationResult(
        method="semiparametric",
        linear=model,
        simulate=lambda x: model.simulate(nonlinearity(x)),
        order=options.order,
        nonlinearity=nonlinearity,
        extra=extra,
    )


def _number(x: float) -> int | float:
    return int(x) if float(x).is_integer() else float(x)
