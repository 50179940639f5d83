"""Confidence bounds of identified models: the estimator's covariance, propagated to what it reports.

Every method's estimate is a smooth function of a parameter vector theta_hat (regression
coefficients, or those and a second stage). The bounds are made in two steps:

1. **Cov(theta_hat)** from the estimator's own first-order (sandwich) expansion. An estimator
   theta_hat = M z (least squares: M = (Phi^T Phi)^-1 Phi^T; instrumental variables:
   M = (Z^T Phi)^-1 Z^T) has theta_hat - theta_0 = M e exactly, e the equation error at the true
   theta_0, i.e. a sum over samples of influences psi_k = M_k e_k. Its covariance is estimated by
   **batch means** (non-overlapping-batch HAC; Flegal & Jones, Ann. Stat. 2010; the block
   estimator of the long-run variance behind the block bootstrap, Kuensch, Ann. Stat. 1989):
   the record is cut into B contiguous blocks, the influences summed per block, and

       Cov(theta_hat) = B / (B - 1) sum_b (g_b - g_mean)(g_b - g_mean)^T.

   It needs neither white nor Gaussian equation errors nor independence of noise and
   regressors beyond the block length: the equation error of an ARX fit to output noise is
   MA(n), a Hammerstein map's distortion is non-Gaussian and depends on the input - the plain
   sigma^2 (Phi^T Phi)^-1 is wrong for both (for CLS on paper 000's cubic map the distortion's
   E[d^2 v^2] is 7x the E[d^2] E[v^2] that independence would give).
   B = ``BLOCKS`` (32) gives the sd to about 13 % (B - 1 degrees of freedom).
2. **First-order propagation** (the delta method; Hjalmarsson & Maartensson, "A geometric
   approach to variance analysis in system identification", IEEE TAC 56(5), 2011, for smooth
   functions of the parameters such as poles and zeros): Cov(g(theta_hat)) = J Cov J^T, with J
   the derivative of the reported quantity g (poles, zeros, gain, the map's parameters) taken
   numerically along the columns of a square root L of Cov (L L^T = Cov): the columns of J L are
   (g(theta_hat + eps L_l) - g(theta_hat)) / eps. One evaluation of g per rank of Cov, steps of
   ``STEP`` standard deviations (linear in practice, far above rounding).

A real pole's sd_im is 0: to first order a simple real root of a real polynomial (or of a real
matrix) moves along the real axis; a pair near a double real root, which the noise may split
into a complex pair, shows as a large sd_re instead. A conjugate pair's two members get the
same sds. The map's ``points_std`` is sqrt(g(u)^T Cov_map g(u)) at each point, g(u) the
gradient of F(u) in the map's parameters (the maps are linear in them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

BLOCKS = 32  # batch means: blocks of the record (the sd to ~13 %)
MIN_BLOCK = 16  # samples per block at least (fewer blocks on a short record)
STEP = 1e-3  # numerical derivative step, in standard deviations along a square root of Cov
RANK_TOLERANCE = 1e-12  # eigenvalues of Cov below this x the largest are dropped from its square root
CLS_HOW = "cls: batch means over {blocks} blocks of both steps' influences, first-order propagation"


@dataclass(frozen=True, eq=False)
class Uncertainty:
    """The sds of an estimate: ``poles_std`` and ``zeros_std`` ([sd_re, sd_im] per root, in the
    order of the model's poles and zeros), ``gain_std`` (of the method's gain figure) and the
    covariance of the input map's parameters (those ``static_maps.map_parameters`` packs:
    polynomial coefficients; piecewise-linear knot values and outer slopes), with ``how`` it
    was made (docs/methods.md)."""

    poles_std: np.ndarray
    zeros_std: np.ndarray
    gain_std: float | None = None
    map_covariance: np.ndarray | None = None
    how: str = ""

    def points_std(self, nonlinearity, u: np.ndarray) -> np.ndarray | None:
        """sd of F(u) at each u: sqrt(g(u)^T Cov_map g(u)), g(u) = dF(u)/d(map parameters)."""
        if self.map_covariance is None or nonlinearity is None:
            return None
        gradient = map_gradient(nonlinearity, np.asarray(u, dtype=float))
        if gradient.shape[1] != self.map_covariance.shape[0]:
            return None
        return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", gradient, self.map_covariance, gradient), 0.0))

    def add_to(self, doc: dict, nonlinearity=None) -> None:
        """The contract's keys into an ``identify`` document: poles_std, zeros_std, gain_std (when
        the document has a gain) and nonlinearity.points_std (one sd per point); a non-finite sd is null."""
        doc["poles_std"] = _finite(np.asarray(self.poles_std, dtype=float).reshape(-1, 2))
        doc["zeros_std"] = _finite(np.asarray(self.zeros_std, dtype=float).reshape(-1, 2))
        if self.gain_std is not None and "gain" in doc:
            doc["gain_std"] = _finite(np.asarray(self.gain_std, dtype=float))
        points = doc.get("nonlinearity", {}).get("points")
        if points:
            sd = self.points_std(nonlinearity, np.asarray(points, dtype=float)[:, 0])
            if sd is not None:
                doc["nonlinearity"]["points_std"] = _finite(sd)
        doc["uncertainty"] = self.how


def _finite(values: np.ndarray):
    """``values.tolist()`` with NaN / inf as None (strict JSON)."""
    return np.where(np.isfinite(values), values, None).tolist()


def guarded(compute: Callable[..., Uncertainty | None], *args) -> Uncertainty | None:
    """``compute(*args)``, or None when the bounds cannot be made (a singular covariance or step-2
    matrix, non-finite data): a model without bounds is still a model."""
    try:
        with np.errstate(all="ignore"):
            return compute(*args)
    except (np.linalg.LinAlgError, ValueError, ZeroDivisionError, FloatingPointError):
        return None


def map_gradient(nonlinearity, u: np.ndarray) -> np.ndarray:
    """dF(u)/dp (len(u) x len(p)) of a map linear in its parameters p (``static_maps.map_parameters``)."""
    from .static_maps import map_parameters

    parameters = map_parameters(nonlinearity)
    zero = parameters.unpack(np.zeros(parameters.size))(u)
    return np.column_stack([parameters.unpack(unit)(u) - zero for unit in np.eye(parameters.size)])


# --- step 1: Cov(theta_hat) -------------------------------------------------------------------


def block_count(samples: int) -> int:
    """BLOCKS, or fewer on a record shorter than BLOCKS x MIN_BLOCK (at least 2)."""
    return int(max(2, min(BLOCKS, samples // MIN_BLOCK)))


def block_sums(influence: np.ndarray, blocks: int) -> np.ndarray:
    """Sums of the rows of ``influence`` (samples x p) over ``blocks`` contiguous blocks of
    (nearly) equal length: a blocks x p array."""
    edges = np.linspace(0, influence.shape[0], blocks + 1).astype(int)[:-1]
    return np.add.reduceat(influence, edges, axis=0)


def batch_means_covariance(block_influences: np.ndarray) -> np.ndarray:
    """Cov of the sum of the influences from their block sums (B x p): B/(B-1) sum (g_b - mean)(...)^T."""
    g = np.asarray(block_influences, dtype=float)
    centred = g - g.mean(axis=0)
    return g.shape[0] / (g.shape[0] - 1) * (centred.T @ centred)


def regression_covariance(phi: np.ndarray, residual: np.ndarray, instruments: np.ndarray | None = None,
                          blocks: int | None = None) -> np.ndarray:
    """Cov(theta_hat) of least squares (``instruments`` None) or of the instrumental-variable
    estimate (Z^T Phi)^-1 Z^T z, by batch means of the influences M_k e_k (module docstring);
    rows in time order, ``residual`` the equation error at theta_hat."""
    z = phi if instruments is None else instruments
    blocks = block_count(phi.shape[0]) if blocks is None else blocks
    scores = block_sums(z * np.asarray(residual, dtype=float)[:, None], blocks)  # sum_k z_k e_k per block
    inverse = np.linalg.pinv(z.T @ phi)
    g = scores @ inverse.T
    return batch_means_covariance(g)


# --- step 2: propagation ----------------------------------------------------------------------


def square_root(covariance: np.ndarray) -> np.ndarray:
    """L (p x r) with L L^T = Cov: its Cholesky factor, or where Cov is singular the symmetric
    eigendecomposition's, r the numerical rank."""
    symmetric = (covariance + covariance.T) / 2.0
    try:
        return np.linalg.cholesky(symmetric)
    except np.linalg.LinAlgError:
        pass
    w, q = np.linalg.eigh(symmetric)
    keep = w > RANK_TOLERANCE * max(float(w.max(initial=0.0)), np.finfo(float).tiny)
    return q[:, keep] * np.sqrt(w[keep])


def _matched(batch: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """Each row of ``batch`` (perturbed roots, r x k) reordered to the nearest of ``nominal`` (k): the
    nearest root per nominal one where that is one-to-one, the closest assignment otherwise (NaN rows
    where a row has another number of roots)."""
    batch, nominal = np.atleast_2d(np.asarray(batch, dtype=complex)), np.asarray(nominal, dtype=complex)
    if batch.shape[1] != nominal.size:
        return np.full((batch.shape[0], nominal.size), np.nan + 0j)
    if nominal.size == 0:
        return batch
    nearest = np.abs(batch[:, None, :] - nominal[None, :, None]).argmin(axis=2)  # r x k
    out = np.take_along_axis(batch, nearest, axis=1)
    for row in np.flatnonzero((np.sort(nearest, axis=1) != np.arange(nominal.size)).any(axis=1)):
        from scipy.optimize import linear_sum_assignment

        rows, cols = linear_sum_assignment(np.abs(nominal[:, None] - batch[row][None, :]))
        out[row, rows] = batch[row, cols]
    return out


Figures = tuple[np.ndarray, np.ndarray, np.ndarray]  # (poles, zeros, other real quantities)


def propagate(figures: Callable[[np.ndarray], Figures], theta: np.ndarray,
              covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(poles_std, zeros_std, Cov of the others) of ``figures(theta_hat)`` by first-order
    propagation of Cov(theta_hat) (module docstring, step 2). Roots are matched to the nominal
    ones (nearest) before differencing; [sd_re, sd_im] per root."""
    theta = np.asarray(theta, dtype=float)
    poles, zeros, others = figures(theta)
    root = square_root(covariance)
    dp = np.zeros((root.shape[1], poles.size), dtype=complex)
    dz = np.zeros((root.shape[1], zeros.size), dtype=complex)
    do = np.zeros((root.shape[1], np.size(others)))
    for i, direction in enumerate(root.T):
        p, z, o = figures(theta + STEP * direction)
        if poles.size:
            dp[i] = _matched(p, poles)[0] - poles
        if zeros.size:
            dz[i] = _matched(z, zeros)[0] - zeros
        do[i] = np.asarray(o) - others
    dp, dz, do = dp / STEP, dz / STEP, do / STEP
    return _root_std(dp), _root_std(dz), do.T @ do


def _root_std(derivatives: np.ndarray) -> np.ndarray:
    """[sd_re, sd_im] per root from the derivatives along the square root's columns (r x roots)."""
    sd = np.column_stack([np.sqrt((derivatives.real**2).sum(axis=0)), np.sqrt((derivatives.imag**2).sum(axis=0))])
    return sd.reshape(-1, 2)


# --- CLS (paper 000 sec. 3.1) -----------------------------------------------------------------


def cls_uncertainty(phi_vv: np.ndarray, phi_yv: np.ndarray, v: np.ndarray, y: np.ndarray, order: int, delay: int,
                    mu: int, basis: np.ndarray,
                    normalised: Callable[[np.ndarray], tuple[float, np.ndarray]], runs=None) -> Uncertainty:
    """The bounds of a CLS estimate (both steps) by batch means of its exact first-order influences.

    Step 1 solves X theta = z on the correlation lags, X and z built from the estimates of
    phi_yv and phi_vv (eq. 8). At the true theta_0 the step-1 residual is
    r(tau) = phi_yv(tau) + sum_j a_j phi_yv(tau - l_j) - sum_i b_i phi_vv(tau - i) - c, and
    theta_hat - theta_0 = X^+ r exactly. Up to edge terms r(tau) = 1/N sum_k w(k) v(k - tau), w the
    raw-data equation error of the step-1 coefficients (eq. 1 or 3), so r is a sum over the
    record's samples and its block sums r_b (each a short cross-correlation, by FFT) give the
    influences g_b = X^+ r_b. This is the correlation estimates' own variance, including the
    fourth-order moments of the non-Gaussian distortion F(v) - C_F v, which Bartlett's formula
    for independent signals leaves out. Poles and zeros depend on step 1 only (on h_d..h_(d+mu-1)
    through ERA for mu-Markov, on (a, b) for ARX).

    Step 2 (gamma = R^+ t, R the basis filtered by B_hat, t = A_hat y) adds its own influences
    (R^T R)^-1 R_k e2_k and those of step 1 through dgamma/dtheta_1 = (R^T R)^-1 R^T D, D the
    derivative of the step-2 residual t - R gamma in the step-1 coefficients: y(k - l_j) for
    a_j, -F_gamma(v(k - i)) for b_i (its dependence through the residual's own correlation
    with D is second order). The gain h_d s(gamma) and the unit-slope map gamma / s(gamma)
    (s = F'(mean v), or the Bussgang gain of a piecewise-linear F) get the joint covariance.

    ``basis`` is step 2's basis of v (its first column the constant), ``normalised`` maps gamma to
    (s, the packed parameters of the unit map gamma / s) (``correlation_least_squares``).

    ``runs`` (several experiments, the correlations made with them): w is formed in every run from
    rest, the blocks cut the centres and step-2 rows that stay in their runs (``_run_blocks``)."""
    from scipy.linalg import lapack

    from .regression import build_regression, filtered_basis, filtered_output, fir_valid, largest_lag, markov_lags
    from .runs import per_run, several

    runs = several(runs)

    v, y = np.asarray(v, dtype=float), np.asarray(y, dtype=float)
    tau_max = (np.size(phi_vv) - 1) // 2
    reg = build_regression(np.asarray(phi_yv, dtype=float), np.asarray(phi_vv, dtype=float), order, delay, mu)
    x = np.column_stack([reg.phi, np.ones(reg.rows.size)])
    qr, tau, _, _ = lapack.dgeqrf(x)
    q, _, _ = lapack.dorgqr(qr, tau)
    pseudo_inverse, _ = lapack.dtrtrs(qr[: x.shape[1], : x.shape[1]], q.T)  # X^+ = R^-1 Q^T (p x rows)
    theta = pseudo_inverse @ reg.target  # the step-1 estimate (``least_squares_qr``, full rank)
    n = order
    a, coefficients = theta[:n], theta[n:-1]
    output_lags, input_lags = markov_lags(order, delay, mu)
    first = largest_lag(order, mu)
    numerator = np.zeros(first + 1)
    numerator[input_lags] = coefficients
    filtered_y = per_run(lambda part: filtered_output(part, output_lags, a), y, runs)  # A_hat y: step 2's target
    w = filtered_y - per_run(lambda part: fir_valid(np.concatenate([np.zeros(first), part])[:, None], numerator)[:, 0],
                             v, runs)  # - B_hat v
    tau = reg.rows - tau_max  # the step-1 rows' lags, ascending
    if runs is None:
        w -= w[first:].mean()
        centres = v.size - 2 * tau_max
        blocks = block_count(centres)
        length = centres // blocks
        lo, hi = int(tau[0]), int(tau[-1])
        span = hi - lo + 1
        starts = tau_max + length * np.arange(blocks)
        w_blocks = w[starts[:, None] + np.arange(length)]
        v_blocks = v[(starts - hi)[:, None] + np.arange(length + span - 1)]
        size = 1 << int(np.ceil(np.log2(length + span - 1)))
        correlation = np.fft.irfft(np.conj(np.fft.rfft(w_blocks, size)) * np.fft.rfft(v_blocks, size), size)
        r_blocks = correlation[:, span - 1 :: -1] / centres  # r_b(tau), tau = lo..hi
        g1 = r_blocks @ pseudo_inverse.T * np.sqrt(centres / (blocks * length))  # the unused tail's share
        edges = np.concatenate([[0], starts[1:] - first])
        step_two = np.arange(first, v.size)
    else:
        blocks, g1, step_two, edges = _run_blocks(runs, w, v, tau, tau_max, first, pseudo_inverse)
    cov1 = batch_means_covariance(g1[:, :-1])

    if mu == 1:
        def roots(t: np.ndarray) -> Figures:
            from .linear import LinearModel

            model = LinearModel(np.concatenate([np.zeros(delay), t[n:]]), np.concatenate([[1.0], t[:n]]))
            return model.poles, model.zeros, np.zeros(0)

        poles_std, zeros_std, _ = propagate(roots, theta[:-1], cov1)
    else:
        markov = np.concatenate([np.zeros(delay), coefficients[:mu]])
        poles_std, zeros_std = era_root_std(markov, order, delay, cov1[n : n + mu, n : n + mu])

    # step 2 and its dependence on step 1, on the rows ``step_two`` (samples k, lags within the run)
    target = filtered_y[step_two]
    regressors = filtered_basis(basis, numerator)  # step 2's regressors (``gain_correction``'s)
    if runs is not None:
        regressors = regressors[step_two - first]
    normal_inverse = np.linalg.inv(regressors.T @ regressors)
    gamma = normal_inverse @ (regressors.T @ target)  # step 2's estimate (a handful of columns: normal equations)
    residual = target - regressors @ gamma
    mapped = basis @ gamma
    lagged_y = y[step_two[:, None] - output_lags[None, :]]
    if runs is None:  # R^T D: the y-lag columns directly, the many map-lag ones by correlations
        shifts = first - input_lags
        map_products = np.array([np.correlate(mapped, column, "valid")[shifts] for column in regressors.T])
    else:
        map_products = regressors.T @ mapped[step_two[:, None] - input_lags[None, :]]
    products = np.column_stack([regressors.T @ lagged_y, -map_products])
    sensitivity = normal_inverse @ products  # dgamma / d(step-1 coefficients), D as in the docstring
    g2 = np.add.reduceat(regressors * residual[:, None], edges, axis=0) @ normal_inverse.T
    joint = np.column_stack([g1[:, n], g2 + g1[:, :-1] @ sensitivity.T])  # (h_d, gamma) per block

    def gain_and_map(t: np.ndarray) -> Figures:
        scale, parameters = normalised(t[1:])
        return np.zeros(0), np.zeros(0), np.concatenate([[t[0] * scale], parameters])

    _, _, cov = propagate(gain_and_map, np.concatenate([[coefficients[0]], gamma]), batch_means_covariance(joint))
    return Uncertainty(poles_std, zeros_std, float(np.sqrt(cov[0, 0])), cov[1:, 1:], CLS_HOW.format(blocks=blocks))


def _run_blocks(runs, w: np.ndarray, v: np.ndarray, tau: np.ndarray, tau_max: int, first: int,
                pseudo_inverse: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """``cls_uncertainty`` on several runs: (blocks, the step-1 influences g_b = X^+ r_b per block, the
    step-2 rows (samples whose lags up to ``first`` stay in their run), the step-2 rows' block edges).
    The centres of the correlations (``Runs.rows(tau_max, tau_max)``) are cut into contiguous blocks
    of nearly equal counts; r_b(tau) = 1/N sum_{k in b} w(k) v(k - tau), N all centres, with w the
    equation error centred over the step-2 rows."""
    step_two = runs.rows(first)
    w = w - w[step_two].mean()
    centres = runs.rows(tau_max, tau_max)
    blocks = block_count(centres.size)
    parts = np.array_split(centres, blocks)
    r_blocks = np.array([w[part] @ v[part[:, None] - tau[None, :]] for part in parts]) / centres.size
    edges = np.searchsorted(step_two, [part[0] for part in parts])
    edges[0] = 0
    return blocks, r_blocks @ pseudo_inverse.T, step_two, edges


def era_root_std(markov: np.ndarray, order: int, delay: int, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(poles_std, zeros_std) of the ERA model (``era``) of ``markov`` = [h_0 .. h_M] given Cov of
    h_delay .. h_M, without an SVD per direction: to first order the rank-n factors of
    H(0) + dH(0) are O + dH(0) C^+ and C + O^+ dH(0) (I - V V^T) (up to a change of state basis,
    which the poles and zeros do not see; O = U S^1/2, C = S^1/2 V^T), so

        dA = O^+ dH(1) C^+ - O^+ dH(0) C^+ A,   dB = O^+ dH(0) (I - V V^T) e_1,   dC = e_1^T dH(0) C^+.

    The realisations A + eps dA, ... along the columns of a square root of Cov give their
    characteristic polynomials P (and numerators N = det(zI - A + BC) - det(zI - A) + D P, the first
    ``delay`` coefficients zero, as ``StateSpaceRealization.to_linear_model``) in a batch, and each
    root z of the estimate moves by dz = -dP(z) / P'(z) (no eigenvalue problem per direction)."""
    from .era import _hankel_indices, _svd

    h = np.asarray(markov, dtype=float)
    available = h.size - 1
    first, second = _hankel_indices((available + 1) // 2, available // 2)
    u, s, vt = _svd(h[first])
    root = np.sqrt(s[:order])
    o_plus, c_plus = (u[:, :order] / root).T, vt[:order].T / root
    a = o_plus @ h[second] @ c_plus
    b, c = root * vt[:order, 0], u[0, :order] * root
    sqrt_cov = square_root(covariance)
    directions = np.zeros((sqrt_cov.shape[1] + 1, h.size))
    directions[1:, h.size - covariance.shape[0]:] = STEP * sqrt_cov.T  # row 0: the estimate itself
    dh0, dh1 = directions[:, first], directions[:, second]
    projector = np.eye(vt.shape[1]) - vt[:order].T @ vt[:order]
    big_a = a + o_plus @ dh1 @ c_plus - o_plus @ dh0 @ c_plus @ a
    big_b = b + np.einsum("ij,rjk,k->ri", o_plus, dh0, projector[:, 0])
    big_c = c + dh0[:, 0, :] @ c_plus
    count = directions.shape[0]  # det(zI - A) and det(zI - A + BC) of every direction in one batch
    both = _characteristic_polynomials(np.concatenate([big_a, big_a - big_b[:, :, None] * big_c[:, None, :]]))
    denominator = both[:count]
    numerator = both[count:] - denominator + (h[0] + directions[:, :1]) * denominator
    numerator[:, :delay] = 0.0
    from .linear import _sorted_roots, eigenvalues

    poles = _sorted_roots(eigenvalues(a).tolist())
    zeros = np.zeros(0, dtype=complex)
    if order > delay:  # the roots of the numerator's n - delay degree part, by its companion matrix
        companion = np.eye(order - delay, k=-1)
        companion[0] = -numerator[0, delay + 1 :] / numerator[0, delay]
        zeros = _sorted_roots(eigenvalues(companion).tolist())
    return _root_std(_root_derivatives(denominator, poles)), _root_std(_root_derivatives(numerator, zeros))


def _characteristic_polynomials(matrices: np.ndarray) -> np.ndarray:
    """det(zI - M) of each matrix of a batch (r x n x n): coefficients of z^n .. z^0 (r x (n + 1)),
    by the Faddeev-LeVerrier recursion M_k = M M_(k-1) + c_(k-1) I, c_k = -tr(M M_k) / k."""
    count, n = matrices.shape[0], matrices.shape[1]
    coefficients = np.zeros((count, n + 1))
    coefficients[:, 0] = 1.0
    power = np.zeros_like(matrices)
    for k in range(1, n + 1):
        power = matrices @ power + coefficients[:, k - 1, None, None] * np.eye(n)
        coefficients[:, k] = -np.trace(matrices @ power, axis1=1, axis2=2) / k
    return coefficients


def _root_derivatives(polynomials: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """dz = -dP(z) / P'(z) for each root z of P = polynomials[0] and each perturbed polynomial
    polynomials[1:] (rows; dP their difference from P over STEP): r x roots."""
    nominal = polynomials[0]
    if roots.size == 0:
        return np.zeros((polynomials.shape[0] - 1, 0), dtype=complex)
    degree = nominal.size - 1
    powers = roots[None, :] ** np.arange(degree, -1, -1)[:, None]  # z^(n-j), j = 0..n
    slope = (nominal[:-1] * np.arange(degree, 0, -1)) @ powers[1:]  # P'(z) = sum_j (n-j) c_j z^(n-j-1)
    return -((polynomials[1:] - nominal) / STEP) @ powers / slope


# --- subseries (methods without a tractable covariance) ---------------------------------------

SEGMENTS = 8  # subseries: contiguous segments of the record, each estimated alone


def subseries_uncertainty(estimate: Callable, v: np.ndarray, y: np.ndarray, result, with_map: bool = True,
                          segments: int = SEGMENTS, runs=None) -> Uncertainty | None:
    """The bounds of an estimator with no tractable covariance, by subseries (Carlstein, Ann. Stat. 14,
    1986; Politis, Romano & Wolf, *Subsampling* 1999): ``estimate`` (v, y) -> result on each of
    ``segments`` contiguous segments of length L (``estimate`` (v, y, runs) -> result: the segment's own
    runs, ``Runs.window``, when the record is of several ``runs``); for a sqrt(N)-consistent estimator
    Cov(full) = Cov(segments) L / N. Roots are matched to ``result``'s. Short segments make it
    conservative (their own bias and transients add to the spread). None when fewer than half the
    segments give an estimate with the same number of poles and zeros."""
    length = v.size // segments
    poles, zeros, others = [], [], []
    from .static_maps import map_parameters

    pack = map_parameters(result.nonlinearity).pack if with_map and result.nonlinearity is not None else None
    for k in range(segments):
        part = slice(k * length, (k + 1) * length)
        try:
            with np.errstate(all="ignore"):
                found = estimate(v[part], y[part], None if runs is None else runs.window(part.start, part.stop))
            extra = [[found.gain]] if result.gain is not None else []
            if pack is not None:
                extra.append(pack(found.nonlinearity))
            figures = np.concatenate(extra) if extra else np.zeros(0)
        except Exception:  # a segment the method rejects (too short, not exciting) is left out
            continue
        if found.poles.size == result.poles.size and found.zeros.size == result.zeros.size:
            poles.append(found.poles)
            zeros.append(found.zeros)
            others.append(figures)
    if len(poles) < segments / 2 or len({np.size(o) for o in others}) > 1:
        return None
    scale = length / v.size
    poles_std = _root_std((_matched(np.array(poles), result.poles) - result.poles) * np.sqrt(scale / (len(poles) - 1)))
    zeros_std = _root_std((_matched(np.array(zeros), result.zeros) - result.zeros) * np.sqrt(scale / (len(poles) - 1)))
    covariance = np.atleast_2d(np.cov(np.array(others).T)) * scale if np.size(others[0]) else np.zeros((0, 0))
    gain_std = float(np.sqrt(covariance[0, 0])) if result.gain is not None else None
    map_covariance = covariance[1:, 1:] if result.gain is not None else covariance
    return Uncertainty(poles_std, zeros_std, gain_std, map_covariance if pack is not None else None,
                       f"subseries over {len(poles)} segments of the record")
