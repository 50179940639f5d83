"""The confidence bounds of the compiled CLS solve (``cls_bounds``, called by ``cls_kernel.cls_solve``):
``uncertainty.cls_uncertainty`` with ``era_root_std`` / ``propagate`` in loops. The equation errors'
block sums through the step-1 pseudo-inverse give the step-1 parameters' batch-means covariance;
first-order changes of the ARX or ERA model along its square root give the poles' and zeros'
standard deviations; step 2's own influences plus step 1's through dgamma/dtheta_1 give the gain's
and the unit-slope map's. Where the reference takes another branch (a root matching beyond
MATCH_BRUTE_FORCE roots, singular normal equations) the status is FALLBACK.
"""

from __future__ import annotations

import numpy as np

from .cls_numerics import (
    CHUNK,
    back_substitute,
    batch_means_covariance,
    dot,
    inverse,
    jit,
    lagged_dots,
    polynomial_roots,
    sorted_roots,
    square_root,
    window_sums,
)
from .uncertainty import BLOCKS, MIN_BLOCK, STEP

OK, FALLBACK = 0, 1
MATCH_BRUTE_FORCE = 4  # roots matched by trying every permutation up to this many (24 permutations)


@jit
def no_bounds(blocks):
    """The bounds left to the reference (status FALLBACK), ``cls_bounds``'s result after ``blocks`` batches."""
    return FALLBACK, np.zeros((0, 2)), np.zeros((0, 2)), 0.0, np.zeros((0, 0)), blocks


@jit
def cls_bounds(v, y, order, delay, mu, tau_max, lags, step_one, step_two, era):
    """``cls_uncertainty`` of a CLS solve of (v, y) with correlations up to lag ``tau_max``: ``lags`` its
    (output lags, input lags), ``step_one`` the step-1 regression's (theta, R, Q^T) (X = Q R),
    ``step_two`` (A_hat y, the regressors B_hat [1, v, .., v^p] (q x rows), the taps of B_hat), ``era``
    the mu-Markov model's (h, A, B, C, eigenvalues of A, U, S, V^T of H(0)) (unused for ARX).
    Returns (status, poles_std, zeros_std, gain_std, map_covariance, blocks)."""
    n, samples = order, v.size
    output_lags, input_lags = lags
    theta, rm, q_transposed = step_one
    filtered_y, regressors, taps = step_two
    first = n + mu - 1
    p, q = theta.size, regressors.shape[0]
    rows1, rows2 = q_transposed.shape[1], regressors.shape[1]
    target = np.ascontiguousarray(filtered_y[first:])
    mean = v.sum() / samples

    # step 1: the block sums r_b(tau) of the equation error w times v(k - tau), through X^+
    w = filtered_y.copy()  # A_hat y - B_hat v (v = 0 before the record; from the largest lag on regressors[1])
    w[first:] -= regressors[1]
    for k in range(first):
        for t in range(k + 1):
            w[k] -= taps[t] * v[k - t]
    w -= w[first:].sum() / rows2
    centres = samples - 2 * tau_max
    blocks = max(2, min(BLOCKS, centres // MIN_BLOCK))
    length = centres // blocks
    lo = first - tau_max  # the step-1 rows' lags lo..tau_max
    r_blocks = np.zeros((blocks, rows1))
    for b in range(blocks):  # r_b(tau) = sum_k w(k) v(k - tau) over the block, tau = lo + t
        start = tau_max + length * b
        lagged_dots(w[start : start + length], v, start - lo, r_blocks[b])
    r_blocks /= centres
    g1 = back_substitute(rm, q_transposed @ r_blocks.T).T * np.sqrt(centres / (blocks * length))  # X^+ r_b
    g1_lin = np.ascontiguousarray(g1[:, : p - 1])
    cov1 = batch_means_covariance(g1_lin)
    if mu == 1:
        ok, poles_std, zeros_std = _arx_root_std(theta[: p - 1].copy(), cov1, order, delay)
    else:
        taps_cov = np.ascontiguousarray(cov1[n : n + mu, n : n + mu])  # of h_d .. h_(d+mu-1)
        ok, poles_std, zeros_std = _era_root_std(order, delay, taps_cov, *era)
    if not ok:
        return no_bounds(blocks)

    # step 2: its own influences and step 1's through dgamma/dtheta_1 (normal equations)
    gram = regressors @ regressors.T
    normal_inverse, ok = inverse(gram)
    if not ok:
        return no_bounds(blocks)
    gamma_n = normal_inverse @ (regressors @ target)
    residual = target - gamma_n @ regressors
    mapped = np.full(samples, gamma_n[q - 1])  # F_gamma(v) by Horner's rule
    for power in range(q - 2, -1, -1):
        for k in range(samples):
            mapped[k] = mapped[k] * v[k] + gamma_n[power]
    # R^T D over chunks of CHUNK rows: the output lags mu..mu+n-1 and the input lags d..n+mu-1 are consecutive
    # (the constant regressor's: its value times sums of windows)
    lagged_y, lagged_map = np.zeros((q, n)), np.zeros((q, input_lags.size))
    window_sums(y, first - output_lags[0], rows2, lagged_y[0])
    window_sums(mapped, first - input_lags[0], rows2, lagged_map[0])
    lagged_y[0] *= regressors[0, 0]
    lagged_map[0] *= regressors[0, 0]
    for begin in range(0, rows2, CHUNK):
        end = min(begin + CHUNK, rows2)
        for e in range(1, q):
            lagged_dots(regressors[e, begin:end], y, first - output_lags[0] + begin, lagged_y[e])
            lagged_dots(regressors[e, begin:end], mapped, first - input_lags[0] + begin, lagged_map[e])
    products = np.empty((q, n + input_lags.size))
    products[:, :n], products[:, n:] = lagged_y, -lagged_map
    sensitivity = normal_inverse @ products
    scores = np.zeros((blocks, q))
    for b in range(blocks):
        begin = 0 if b == 0 else tau_max + length * b - first
        end = rows2 if b == blocks - 1 else tau_max + length * (b + 1) - first
        for e in range(q):
            scores[b, e] = dot(regressors[e, begin:end], residual[begin:end])
    joint = np.empty((blocks, q + 1))
    joint[:, 0] = g1[:, n]
    joint[:, 1:] = scores @ normal_inverse.T + g1_lin @ sensitivity.T

    # the gain h_d s(gamma) and the unit-slope map gamma / s(gamma) (``propagate``)
    powers = np.zeros(q)
    for power in range(1, q):
        powers[power] = power * mean ** (power - 1)
    estimate = np.empty(q + 1)
    estimate[0] = theta[n]  # h_d
    estimate[1:] = gamma_n
    root = square_root(batch_means_covariance(joint))
    nominal = _gain_and_map(estimate, powers)
    changes = np.empty((root.shape[1], q + 1))
    for i in range(root.shape[1]):
        changes[i] = (_gain_and_map(estimate + STEP * root[:, i], powers) - nominal) / STEP
    cov = changes.T @ changes
    return OK, poles_std, zeros_std, np.sqrt(cov[0, 0]), cov[1:, 1:].copy(), blocks


@jit
def _characteristic_polynomials(matrices):
    """``uncertainty._characteristic_polynomials``: det(zI - M) of each of a batch by Faddeev-LeVerrier,
    M_k = M M_(k-1) + c_(k-1) I, c_k = -tr(M M_k) / k (loops: the matrices are a few rows)."""
    count, n = matrices.shape[0], matrices.shape[1]
    coefficients = np.zeros((count, n + 1))
    power, product = np.zeros((n, n)), np.zeros((n, n))
    for r in range(count):
        m = matrices[r]
        coefficients[r, 0] = 1.0
        power[:] = 0.0
        for k in range(1, n + 1):
            for i in range(n):  # product = M power + c_(k-1) I, then power = product
                for j in range(n):
                    total = coefficients[r, k - 1] if i == j else 0.0
                    for t in range(n):
                        total += m[i, t] * power[t, j]
                    product[i, j] = total
            power[:] = product
            trace = 0.0
            for i in range(n):
                for t in range(n):
                    trace += m[i, t] * power[t, i]
            coefficients[r, k] = -trace / k
    return coefficients


@jit
def _root_std(derivatives):
    """[sd_re, sd_im] per root from the derivatives along the square root's columns (r x roots)."""
    out = np.zeros((derivatives.shape[1], 2))
    for i in range(derivatives.shape[1]):
        re, im = 0.0, 0.0
        for r in range(derivatives.shape[0]):
            re += derivatives[r, i].real ** 2
            im += derivatives[r, i].imag ** 2
        out[i, 0], out[i, 1] = np.sqrt(re), np.sqrt(im)
    return out


@jit
def _root_derivatives(polynomials, roots):
    """``uncertainty._root_derivatives``: dz = -dP(z) / P'(z) per perturbed polynomial (rows 1..) and root."""
    count, size = polynomials.shape[0] - 1, polynomials.shape[1]
    degree = size - 1
    out = np.zeros((count, roots.size), np.complex128)
    for i in range(roots.size):
        z = roots[i]
        powers = np.empty(size, np.complex128)  # z^(degree - j)
        powers[degree] = 1.0
        for j in range(degree - 1, -1, -1):
            powers[j] = powers[j + 1] * z
        slope = 0j
        for j in range(degree):
            slope += polynomials[0, j] * (degree - j) * powers[j + 1]
        for r in range(count):
            change = 0j
            for j in range(size):
                change += (polynomials[r + 1, j] - polynomials[0, j]) / STEP * powers[j]
            out[r, i] = -change / slope
    return out


@jit
def _matched(batch, nominal):
    """``uncertainty._matched`` for one row: the nearest of ``batch`` per nominal root where that is
    one-to-one, else the assignment of least total distance (every permutation); ok False beyond
    MATCH_BRUTE_FORCE roots."""
    k = nominal.size
    nearest = np.empty(k, np.int64)
    seen = np.zeros(k, np.bool_)
    unique = True
    for i in range(k):
        best, index = np.inf, 0
        for j in range(k):
            d = abs(batch[j] - nominal[i])
            if d < best:
                best, index = d, j
        nearest[i] = index
        if seen[index]:
            unique = False
        seen[index] = True
    if unique:
        return batch[nearest], True
    if k > MATCH_BRUTE_FORCE:
        return batch, False
    permutation = np.arange(k)
    best_cost, best = np.inf, permutation.copy()
    while True:
        cost = 0.0
        for i in range(k):
            cost += abs(nominal[i] - batch[permutation[i]])
        if cost < best_cost:
            best_cost, best = cost, permutation.copy()
        i = k - 2  # the next permutation in lexicographic order
        while i >= 0 and permutation[i] >= permutation[i + 1]:
            i -= 1
        if i < 0:
            break
        j = k - 1
        while permutation[j] <= permutation[i]:
            j -= 1
        permutation[i], permutation[j] = permutation[j], permutation[i]
        permutation[i + 1 :] = permutation[i + 1 :][::-1].copy()
    return batch[best], True


@jit
def _era_root_std(order, delay, covariance, h, a, b, c, eigenvalues, u, s, vt):
    """``uncertainty.era_root_std``: (ok, poles_std, zeros_std) of the ERA model (A, B, C and A's
    eigenvalues from ``cls_kernel._era``, U S V^T its H(0)) given Cov of h_delay .. h_M. The first-order changes

        dA = O^+ dH(1) C^+ - O^+ dH(0) C^+ A,   dB = O^+ dH(0) (I - V V^T) e_1,   dC = e_1^T dH(0) C^+

    are linear in the Markov parameters' change dh: with K_m = sum_(i+j=m) O^+[:, i] C^+[j, :] (and
    k_m likewise with (I - V V^T) e_1), O^+ dH(0) C^+ = sum_m dh_(1+m) K_m and O^+ dH(1) C^+ = sum_m
    dh_(2+m) K_m, a few multiplications per direction instead of the Hankel products."""
    available = h.size - 1
    rows, columns = (available + 1) // 2, available // 2
    root = np.sqrt(s[:order])
    o_plus = (u[:, :order] / root).T
    c_plus = vt[:order].T / root
    projector_first = -vt[:order].T @ np.ascontiguousarray(vt[:order, 0])  # (I - V V^T) e_1
    projector_first[0] += 1.0
    span = rows + columns - 1
    k_a, k_b = np.zeros((order, order, span)), np.zeros((order, span))  # K_m[p, q] as k_a[p, q, m]
    for i in range(rows):
        for j in range(columns):
            for p in range(order):
                k_b[p, i + j] += o_plus[p, i] * projector_first[j]
                for q in range(order):
                    k_a[p, q, i + j] += o_plus[p, i] * c_plus[j, q]
    c_plus_t = np.ascontiguousarray(c_plus.T)
    sqrt_cov = square_root(covariance)
    count = sqrt_cov.shape[1] + 1
    directions = np.zeros((count, h.size))
    directions[1:, h.size - covariance.shape[0] :] = STEP * sqrt_cov.T
    matrices = np.empty((2 * count, order, order))
    first_part, second_part = np.empty((order, order)), np.empty((order, order))  # O^+ dH(0) C^+, O^+ dH(1) C^+
    big_b, big_c = np.empty(order), np.empty(order)
    for r in range(count):
        d0, d1 = directions[r, 1 : 1 + span], directions[r, 2 : 2 + span]  # dh_(1+m), dh_(2+m)
        for p in range(order):
            for q in range(order):
                first_part[p, q] = dot(d0, k_a[p, q])
                second_part[p, q] = dot(d1, k_a[p, q])
            big_b[p] = b[p] + dot(d0, k_b[p])
            big_c[p] = c[p] + dot(d0[:columns], c_plus_t[p])
        for p in range(order):
            for q in range(order):
                change = second_part[p, q]
                for t in range(order):
                    change -= first_part[p, t] * a[t, q]
                matrices[r, p, q] = a[p, q] + change
        for p in range(order):
            for q in range(order):
                matrices[count + r, p, q] = matrices[r, p, q] - big_b[p] * big_c[q]
    both = _characteristic_polynomials(matrices)
    denominator = both[:count]
    numerator = both[count:] - denominator
    for r in range(count):
        numerator[r] += (h[0] + directions[r, 0]) * denominator[r]
        numerator[r, :delay] = 0.0
    poles = sorted_roots(eigenvalues)
    zeros = np.zeros(0, np.complex128)
    if order > delay:
        zeros, ok = polynomial_roots(numerator[0, delay:])
        if not ok:
            return False, np.zeros((0, 2)), np.zeros((0, 2))
    return (True, _root_std(_root_derivatives(denominator, poles)),
            _root_std(_root_derivatives(numerator[:, delay:], zeros)))


@jit
def _arx_root_std(theta, covariance, order, delay):
    """``propagate`` of the ARX model's poles and zeros (LinearModel of theta = [a | b_d..b_n]):
    (ok, poles_std, zeros_std), roots of each perturbed model matched to the nominal ones."""
    n = order
    denominator = np.empty(n + 1)
    denominator[0] = 1.0
    denominator[1:] = theta[:n]
    poles, ok_p = polynomial_roots(denominator)
    zeros, ok_z = polynomial_roots(theta[n:])
    if not (ok_p and ok_z):
        return False, np.zeros((0, 2)), np.zeros((0, 2))
    root = square_root(covariance)
    dp = np.zeros((root.shape[1], poles.size), np.complex128)
    dz = np.zeros((root.shape[1], zeros.size), np.complex128)
    for i in range(root.shape[1]):
        t = theta + STEP * root[:, i]
        denominator[1:] = t[:n]
        p, ok_p = polynomial_roots(denominator)
        z, ok_z = polynomial_roots(t[n:])
        if not (ok_p and ok_z):
            return False, np.zeros((0, 2)), np.zeros((0, 2))
        p, ok_p = _matched(p, poles)
        z, ok_z = _matched(z, zeros)
        if not (ok_p and ok_z):
            return False, np.zeros((0, 2)), np.zeros((0, 2))
        dp[i] = (p - poles) / STEP
        dz[i] = (z - zeros) / STEP
    return True, _root_std(dp), _root_std(dz)


@jit
def _gain_and_map(t, powers):
    """[h_d s, gamma / s] of t = [h_d, gamma], s = F'(mean v) = powers . gamma."""
    scale = np.dot(powers, t[1:])
    out = np.empty(t.size)
    out[0] = t[0] * scale
    out[1:] = t[1:] / scale
    return out
