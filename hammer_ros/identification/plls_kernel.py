"""The PLLS-Hammerstein solve of paper 001 (sec. 4.1) with its instrumental-variable passes and its
confidence bounds, as one numba kernel (``plls_solve``): the same arithmetic as the numpy reference
(``piecewise_linear_ls.plls(structure="hammerstein", instrumental=True, uncertainty=True)``: the
point-slope regression of eq. 23, least squares, ``INSTRUMENT_PASSES`` passes of ``_instrumental_step``,
the rank-one factors of eqs. 35-38 with the unit-gain beta, and ``plls_uncertainty``'s batch means and
first-order propagation), in loops and a few LAPACK calls instead of ~1500 numpy calls (the
propagation rebuilds the blocks once per direction of the covariance's square root: 26 directions
for order 2 and 10 breakpoints). Equal to the reference to rounding (the tests compare estimates and
bounds to 1e-9 relative): least squares by Householder QR where the reference takes the SVD, sums
in another order.

Covered: the Hammerstein structure, one run, no reference (closed loop), beta None. Where the
reference takes another branch (too few rows, a nearly rank-deficient regression, non-finite data,
roots at 0, a root matching beyond 4 roots) the kernel returns status FALLBACK (bounds_status
FALLBACK: the bounds alone) and the caller runs the reference.

Imported on the first compiled solve only; ``nogil=True`` and ``cache=True`` as ``cls_kernel``, whose
``callee_digest`` covers this kernel's callees too (the same two modules).
"""

from __future__ import annotations

import numba
import numpy as np

from .cls_bounds_kernel import FALLBACK, OK, _matched, _root_std
from .cls_kernel import CALLEE_DIGEST, callee_digest
from .cls_numerics import all_finite, batch_means_covariance, householder_solve, jit, polynomial_roots, square_root
from .uncertainty import BLOCKS, MIN_BLOCK, STEP

COND_LIMIT = 1e12  # ``_instrumental_step``: Z^T Phi above this condition number keeps the previous pass


@jit
def _basis(x, partition, primary):
    """``point_slope_basis``: eta_i(x) = clip(x, c_(i-1), c_i) - clip(c_r, c_(i-1), c_i), len(x) x (p+1)."""
    width = partition.size + 1
    out = np.empty((x.size, width))
    centre = partition[primary - 1]
    for i in range(width):
        lo = -np.inf if i == 0 else partition[i - 1]
        hi = np.inf if i == width - 1 else partition[i]
        offset = min(max(centre, lo), hi)
        for k in range(x.size):
            out[k, i] = min(max(x[k], lo), hi) - offset
    return out


@jit
def _columns(output, eta, order, delay):
    """Phi^T of eq. 23 (``_regression``): rows [-output(k - j)] j = 1..n, [eta(k - i)] i = delay..n
    (lag-major), 1, for k = n..N-1: a (n + n_b (p+1) + 1) x (N - n) array."""
    rows, width = output.size - order, eta.shape[1]
    lags = order - delay + 1
    out = np.empty((order + lags * width + 1, rows))
    for j in range(order):
        for k in range(rows):
            out[j, k] = -output[order + k - j - 1]
    for i in range(lags):
        lag = delay + i
        for k in range(rows):
            source = eta[order + k - lag]
            for c in range(width):
                out[order + i * width + c, k] = source[c]
    out[-1] = 1.0
    return out


@jit
def _factors(theta, order, delay, width, knot_basis):
    """``_hammerstein_factors`` with the default beta (eqs. 35-38): (ok, a, b_delay..b_n, mu, kappa,
    the map's figures [f(c_1)..f(c_p), mu_1, mu_(p+1)], poles, zeros); ok False where a root count
    would differ from the reference's (a leading or trailing coefficient 0)."""
    lags = order - delay + 1
    a = theta[:order].copy()
    matrix = np.empty((width, lags))  # vec^-1(theta_B) (p+1) x n_b
    for i in range(lags):
        for c in range(width):
            matrix[c, i] = theta[order + i * width + c]
    left, sigma, right_t = np.linalg.svd(matrix, full_matrices=False)
    u1, v1 = left[:, 0].copy(), right_t[0].copy()
    if v1.sum() < 0:
        u1, v1 = -u1, -v1
    total_v, total_a, scale = v1.sum(), 1.0 + a.sum(), 1.0 + np.abs(a).sum()
    beta = 1.0 if abs(total_v) < 1e-9 or abs(total_a) < 1e-9 * scale else total_v / total_a
    b = v1 / beta
    mu = beta * sigma[0] * u1
    kappa = theta[-1] / b.sum()
    figures = np.empty(knot_basis.shape[0] + 2)
    figures[: knot_basis.shape[0]] = knot_basis @ mu + kappa
    figures[-2], figures[-1] = mu[0], mu[-1]
    denominator = np.empty(order + 1)
    denominator[0] = 1.0
    denominator[1:] = a
    poles, ok_p = polynomial_roots(denominator)
    zeros, ok_z = polynomial_roots(b)
    return ok_p and ok_z, a, b, mu, kappa, figures, poles, zeros


@jit
def _simulate(u, partition, figures, a, b, delay):
    """``simulate_hammerstein`` of the estimate: f(u) (``PiecewiseLinearMap``: interpolation between
    the knots, the outer slopes beyond), then ``lfilter`` (direct form II transposed) through B/A."""
    p = partition.size
    mapped = np.interp(u, partition, figures[:p])
    for k in range(u.size):
        if u[k] < partition[0]:
            mapped[k] = figures[0] + figures[p] * (u[k] - partition[0])
        elif u[k] > partition[p - 1]:
            mapped[k] = figures[p - 1] + figures[p + 1] * (u[k] - partition[p - 1])
    n = a.size
    numerator = np.zeros(n + 1)
    numerator[delay:] = b
    state = np.zeros(n + 1)
    out = np.empty(u.size)
    for k in range(u.size):
        x = mapped[k]
        value = numerator[0] * x + state[0]
        for i in range(n - 1):
            state[i] = numerator[i + 1] * x + state[i + 1] - a[i] * value
        state[n - 1] = numerator[n] * x - a[n - 1] * value
        out[k] = value
    return out


@numba.njit(cache=callee_digest() == CALLEE_DIGEST, nogil=True)
def plls_solve(u, y, partition, primary, order, delay, passes, bounds):
    """PLLS-Hammerstein by least squares and ``passes`` IV passes on the partition c with the
    primary index r (1-based) and, with ``bounds``, ``plls_uncertainty``. Returns (status, a, b_delay..b_n,
    mu, kappa, instrumented, bounds_status, poles_std, zeros_std, map_covariance); ``instrumented``:
    an IV pass was taken (the bounds are those of the IV estimate)."""
    none2 = np.zeros((0, 2))
    failed = (FALLBACK, np.zeros(0), np.zeros(0), np.zeros(0), 0.0, False, FALLBACK, none2, none2, np.zeros((0, 0)))
    width = partition.size + 1
    size = order + (order - delay + 1) * width + 1
    rows = u.size - order
    if (not (all_finite(u) and all_finite(y) and all_finite(partition)) or order < 1 or delay < 0
            or delay > order or rows <= size or not 1 <= primary <= partition.size):
        return failed
    eta = _basis(u, partition, primary)
    knot_basis = _basis(partition, partition, primary)
    phi_t = _columns(y, eta, order, delay)
    phi = np.ascontiguousarray(phi_t.T)
    target = np.ascontiguousarray(y[order:])
    theta = householder_solve(phi_t, target).copy()  # eq. 33 (contiguous)
    if theta.size == 0:
        return failed
    ok, a, b, mu, kappa, figures, poles, zeros = _factors(theta, order, delay, width, knot_basis)
    if not ok:
        return failed
    instruments_t, accepted = phi_t, np.zeros((0, 0))  # Z^T and the last pass's Z^T Phi
    instrumented = False
    for _ in range(passes):  # ``_instrumental_step``
        stable = True
        for pole in poles:
            stable = stable and abs(pole) < 1.0
        if not stable:
            break  # as above
        candidate_t = _columns(_simulate(u, partition, figures, a, b, delay), eta, order, delay)
        normal = candidate_t @ phi
        if not all_finite(normal.ravel()) or np.linalg.cond(normal) > COND_LIMIT:
            break  # the reference keeps (Z, theta~): the next pass would see the same estimate
        instruments_t, accepted, instrumented = candidate_t, normal, True
        theta = np.linalg.solve(normal, candidate_t @ target)
        ok, a, b, mu, kappa, figures, poles, zeros = _factors(theta, order, delay, width, knot_basis)
        if not ok:
            return failed
    if not bounds:
        return OK, a, b, mu, kappa, instrumented, FALLBACK, none2, none2, np.zeros((0, 0))

    # Cov(theta~) by batch means of the influences (``regression_covariance``)
    residual = target - phi @ theta
    blocks = max(2, min(BLOCKS, rows // MIN_BLOCK))
    step = rows / blocks
    scores = np.zeros((blocks, size))
    for block in range(blocks):
        begin, end = int(block * step), rows if block == blocks - 1 else int((block + 1) * step)
        for e in range(size):
            column = instruments_t[e]
            total = 0.0
            for k in range(begin, end):
                total += column[k] * residual[k]
            scores[block, e] = total
    normal = accepted if instrumented else phi_t @ phi
    covariance = batch_means_covariance(scores @ np.linalg.pinv(normal).T)

    # first-order propagation to the poles, zeros and the map's figures (``propagate``)
    root = square_root(covariance)
    dp = np.zeros((root.shape[1], poles.size), np.complex128)
    dz = np.zeros((root.shape[1], zeros.size), np.complex128)
    do = np.zeros((root.shape[1], figures.size))
    for i in range(root.shape[1]):
        ok, _, _, _, _, moved, p, z = _factors(theta + STEP * root[:, i], order, delay, width, knot_basis)
        if not ok or p.size != poles.size or z.size != zeros.size:
            return OK, a, b, mu, kappa, instrumented, FALLBACK, none2, none2, np.zeros((0, 0))
        p, ok_p = _matched(p, poles)
        z, ok_z = _matched(z, zeros)
        if not (ok_p and ok_z):
            return OK, a, b, mu, kappa, instrumented, FALLBACK, none2, none2, np.zeros((0, 0))
        dp[i] = (p - poles) / STEP
        dz[i] = (z - zeros) / STEP
        do[i] = (moved - figures) / STEP
    return OK, a, b, mu, kappa, instrumented, OK, _root_std(dp), _root_std(dz), do.T @ do
