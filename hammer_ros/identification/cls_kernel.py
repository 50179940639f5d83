# One module: numba's cache (cache=True) checks only the caller's file, so cls_solve's callees stay beside it.
"""The CLS solve of paper 000 (sec. 3.1) from the correlation functions, with its confidence
bounds, as one numba kernel (``cls_solve``): the same arithmetic as the numpy reference
(``correlation_least_squares.correlation_least_squares_steps`` for the estimate,
``uncertainty.cls_uncertainty`` with ``era_root_std`` / ``propagate`` for the bounds), in loops
and a few LAPACK calls instead of ~150 numpy calls. Equal to the reference to rounding (the
tests compare estimates and bounds to 1e-9 relative); its sums run in another order, so the last
digits differ.

Covered: a polynomial F (no partition), open loop (no instrument), ARX (mu = 1) and mu-Markov.
Where the reference takes another branch (a nearly rank-deficient regression, an ERA of too low a
rank, an F without slope, non-finite data, a root matching beyond 4 roots) the kernel returns
status FALLBACK and the caller runs the reference, which raises or answers as before.

Imported on the first compiled solve only (``import hammer_ros`` stays light, as
``compiled_loops``); compiled with ``cache=True`` (numba's cache beside this file: a process
after the first loads the machine code) and ``nogil=True`` (solves of several channels may run
in threads at once).
"""

from __future__ import annotations

import numba
import numpy as np

from .regression import QR_RANK_TOLERANCE
from .uncertainty import BLOCKS, MIN_BLOCK, RANK_TOLERANCE, STEP

OK, FALLBACK = 0, 1
MATCH_BRUTE_FORCE = 4  # roots matched by trying every permutation up to this many (24 permutations)
_TINY = np.finfo(np.float64).tiny

_jit = numba.njit(cache=True, nogil=True)


# --- the long loops: each a whole function (not a call per sum), their sums reassociated so that the
# compiler vectorises them (NaN and inf kept)

CHUNK = 512  # samples per pass of the long loops: their operands stay in the L1 cache across the taps / lags
_fast = numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})


@_jit
def _axpy(out, alpha, x):
    """out += alpha x, element by element (out and x of one length)."""
    for k in range(out.size):
        out[k] += alpha * x[k]


@_fast
def _dot(x, z):
    """x . z."""
    total = 0.0
    for k in range(x.size):
        total += x[k] * z[k]
    return total


@_fast
def _lagged_dots(x, z, start, out):
    """out[t] += sum_i x[i] z[start - t + i] for t < out.size (start - t >= 0): x against z at consecutive
    lags, four lags per pass over x."""
    n = x.size
    t = 0
    while t + 4 <= out.size:
        z0, z1 = z[start - t : start - t + n], z[start - t - 1 : start - t - 1 + n]
        z2, z3 = z[start - t - 2 : start - t - 2 + n], z[start - t - 3 : start - t - 3 + n]
        s0 = s1 = s2 = s3 = 0.0
        for i in range(n):
            s0 += x[i] * z0[i]
            s1 += x[i] * z1[i]
            s2 += x[i] * z2[i]
            s3 += x[i] * z3[i]
        out[t] += s0
        out[t + 1] += s1
        out[t + 2] += s2
        out[t + 3] += s3
        t += 4
    for rest in range(t, out.size):
        window = z[start - rest : start - rest + n]
        total = 0.0
        for i in range(n):
            total += x[i] * window[i]
        out[rest] += total


@_fast
def _all_finite(x):
    """No NaN or inf in x (x * 0 is NaN for both)."""
    total = 0.0
    for k in range(x.size):
        total += x[k] * 0.0
    return total == 0.0


@_jit
def _window_sums(z, start, length, out):
    """out[t] = sum_i z[start - t + i], i < length, for t < out.size: one window summed, then moved."""
    total = 0.0
    for i in range(length):
        total += z[start + i]
    out[0] = total
    for t in range(1, out.size):
        total += z[start - t] - z[start - t + length]
        out[t] = total


@_fast
def _fir(x, taps, rows, out):
    """out[k] += sum_t taps[t] x[k + m - 1 - t], k < rows (np.convolve(x, taps, "valid")), four taps per pass
    over chunks of CHUNK outputs."""
    m = taps.size
    for begin in range(0, rows, CHUNK):
        end = min(begin + CHUNK, rows)
        chunk = out[begin:end]
        t = 0
        while t + 4 <= m:
            c0, c1, c2, c3 = taps[t], taps[t + 1], taps[t + 2], taps[t + 3]
            shift = m - 1 - t
            x0, x1 = x[begin + shift : end + shift], x[begin + shift - 1 : end + shift - 1]
            x2, x3 = x[begin + shift - 2 : end + shift - 2], x[begin + shift - 3 : end + shift - 3]
            for k in range(chunk.size):
                chunk[k] += c0 * x0[k] + c1 * x1[k] + c2 * x2[k] + c3 * x3[k]
            t += 4
        for rest in range(t, m):
            window = x[begin + m - 1 - rest : end + m - 1 - rest]
            for k in range(chunk.size):
                chunk[k] += taps[rest] * window[k]


# --- small linear algebra ------------------------------------------------------------------------


@_jit
def _lags(order, delay, mu):
    """``regression.markov_lags``: output lags mu..mu+n-1, input lags d..d+mu-1 and d+1+mu-1..n+mu-1."""
    output = np.arange(1, order + 1) + mu - 1
    inputs = np.empty(mu + order - delay, np.int64)
    inputs[:mu] = np.arange(delay, delay + mu)
    inputs[mu:] = np.arange(delay + 1, order + 1) + mu - 1
    return output, inputs


@_jit
def _back_substitute(r, rhs):
    """R^-1 rhs for an upper-triangular R (n x n) and rhs (n x m), row by row."""
    n = r.shape[0]
    out = rhs.copy()
    for i in range(n - 1, -1, -1):
        row = out[i]
        for j in range(i + 1, n):
            factor = r[i, j]
            other = out[j]
            for k in range(row.size):
                row[k] -= factor * other[k]
        scale = r[i, i]
        for k in range(row.size):
            row[k] /= scale
    return out


@_jit
def _well_conditioned(r):
    """``regression.least_squares_qr``'s check: min |r_ii| > QR_RANK_TOLERANCE max |r_jj| (finite)."""
    diagonal = np.abs(np.diag(r))
    return diagonal.min() > QR_RANK_TOLERANCE * diagonal.max()


@_jit
def _householder_solve(columns, target):
    """theta minimising ||target - A theta|| with A's columns the rows of ``columns`` (q x N), by
    Householder QR of [A | target] (``least_squares_qr``); an empty array when R fails its rank check."""
    q, rows = columns.shape
    m = np.empty((q + 1, rows))
    m[:q] = columns
    m[q] = target
    r = np.zeros((q, q))
    for j in range(q):
        x = m[j, j:]
        norm = np.sqrt(_dot(x, x))
        alpha = -norm if x[0] >= 0.0 else norm
        x[0] -= alpha  # x is now the reflector's vector v; H = I - 2 v v^T / v^T v
        beta = _dot(x, x)
        for c in range(j + 1, q + 1):
            factor = 2.0 * _dot(x, m[c, j:]) / beta if beta > 0.0 else 0.0
            _axpy(m[c, j:], -factor, x)
        r[j, j] = alpha
        for c in range(j + 1, q):
            r[j, c] = m[c, j]
    if not _well_conditioned(r):
        return np.zeros(0)
    rhs = np.empty((q, 1))
    rhs[:, 0] = m[q, :q]
    return _back_substitute(r, rhs)[:, 0]


@_jit
def _inverse(a):
    """(a^-1, True) by Gauss-Jordan elimination with partial pivoting, or (zeros, False) for a singular
    or non-finite a (where ``np.linalg.inv`` raises)."""
    n = a.shape[0]
    m = a.copy()
    out = np.eye(n)
    for j in range(n):
        pivot = j
        for i in range(j + 1, n):
            if abs(m[i, j]) > abs(m[pivot, j]):
                pivot = i
        if not (m[pivot, j] != 0.0 and np.isfinite(m[pivot, j])):
            return out, False
        for k in range(n):
            m[j, k], m[pivot, k] = m[pivot, k], m[j, k]
            out[j, k], out[pivot, k] = out[pivot, k], out[j, k]
        scale = m[j, j]
        for k in range(n):
            m[j, k] /= scale
            out[j, k] /= scale
        for i in range(n):
            if i != j:
                factor = m[i, j]
                for k in range(n):
                    m[i, k] -= factor * m[j, k]
                    out[i, k] -= factor * out[j, k]
    return out, True


@_jit
def _cholesky(a):
    """(L, True) with L L^T = a, or (zeros, False) where a is not positive definite (LAPACK dpotrf's test)."""
    n = a.shape[0]
    lower = np.zeros((n, n))
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= lower[j, k] * lower[j, k]
        if not d > 0.0:
            return lower, False
        lower[j, j] = np.sqrt(d)
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= lower[i, k] * lower[j, k]
            lower[i, j] = s / lower[j, j]
    return lower, True


@_jit
def _square_root(covariance):
    """``uncertainty.square_root``: L (p x r), L L^T = Cov, Cholesky or the eigendecomposition's."""
    symmetric = (covariance + covariance.T) / 2.0
    lower, ok = _cholesky(symmetric)
    if ok:
        return lower
    w, vectors = np.linalg.eigh(symmetric)
    largest = max(w.max(), 0.0)
    keep = w > RANK_TOLERANCE * max(largest, _TINY)
    return vectors[:, keep] * np.sqrt(w[keep])


@_jit
def _batch_means_covariance(g):
    """``uncertainty.batch_means_covariance``: B/(B-1) sum_b (g_b - mean)(g_b - mean)^T."""
    blocks = g.shape[0]
    centred = g - (g.sum(axis=0) / blocks)
    return blocks / (blocks - 1) * (centred.T @ centred)


# --- roots -----------------------------------------------------------------------------------------


@_jit
def _eigenvalues(matrix):
    """The eigenvalues of a real square matrix, complex."""
    return np.linalg.eigvals(matrix.astype(np.complex128))


@_jit
def _sorted_roots(roots):
    """``linear._sorted_roots``: imaginary parts below 1e-12 set to 0, ordered by (real, imaginary), stable."""
    out = np.empty(roots.size, np.complex128)
    for i in range(roots.size):
        r = roots[i]
        out[i] = complex(r.real + 0.0, 0.0) if abs(r.imag) < 1e-12 else r
    for i in range(1, out.size):  # insertion sort, stable
        current = out[i]
        j = i - 1
        while j >= 0 and (out[j].real > current.real or (out[j].real == current.real and out[j].imag > current.imag)):
            out[j + 1] = out[j]
            j -= 1
        out[j + 1] = current
    return out


@_jit
def _polynomial_roots(coefficients):
    """The roots of a polynomial (descending powers) by its companion matrix, sorted; an empty array
    with False when its first or last coefficient is 0 (``linear.LinearModel`` then counts roots at 0)."""
    degree = coefficients.size - 1
    if coefficients[0] == 0.0 or coefficients[degree] == 0.0:
        return np.zeros(0, np.complex128), False
    if degree == 0:
        return np.zeros(0, np.complex128), True
    companion = np.zeros((degree, degree))
    for i in range(1, degree):
        companion[i, i - 1] = 1.0
    for j in range(degree):
        companion[0, j] = -coefficients[j + 1] / coefficients[0]
    return _sorted_roots(_eigenvalues(companion)), True


@_jit
def _polynomial_from_roots(roots):
    """``linear.characteristic_polynomial``'s product of z - lambda over the roots (descending powers, real part)."""
    coefficients = np.zeros(roots.size + 1, np.complex128)
    coefficients[0] = 1.0
    for k in range(1, roots.size + 1):
        root = roots[k - 1]
        for i in range(k, 0, -1):
            coefficients[i] -= root * coefficients[i - 1]
    return coefficients.real.copy()


@_jit
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


@_jit
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


@_jit
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


@_jit
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


# --- ERA (era.py) and its root derivatives (uncertainty.era_root_std) ---------------------------------


@_jit
def _hankel(h, rows, columns, offset):
    """H[i, j] = h[offset + i + j]."""
    out = np.empty((rows, columns))
    for i in range(rows):
        for j in range(columns):
            out[i, j] = h[offset + i + j]
    return out


@_jit
def _era(h, order, delay):
    """The ERA realisation of ``era.eigensystem_realization`` (default Hankel size) and its transfer
    function (``to_linear_model``): (ok, A, B, C, eigenvalues of A, numerator, denominator, U, S, V^T of H(0))."""
    available = h.size - 1
    rows, columns = (available + 1) // 2, available // 2
    empty, none = np.zeros((0, 0)), np.zeros(0)
    if rows < 1 or columns < 1 or order < 1 or order > min(rows, columns):
        return False, empty, none, none, none.astype(np.complex128), none, none, empty, none, empty
    u, s, vt = np.linalg.svd(_hankel(h, rows, columns, 1))
    if s[order - 1] <= 1e-14 * max(s[0], _TINY):
        return False, empty, none, none, none.astype(np.complex128), none, none, empty, none, empty
    root = np.sqrt(s[:order])
    un, vn = np.ascontiguousarray(u[:, :order]), np.ascontiguousarray(vt[:order].T)
    a = (un.T @ _hankel(h, rows, columns, 2) @ vn) / np.outer(root, root)
    b = root * vn[0]
    c = un[0] * root
    eigenvalues = _eigenvalues(a)
    denominator = _polynomial_from_roots(eigenvalues)
    numerator = _polynomial_from_roots(_eigenvalues(a - np.outer(b, c))) - denominator + h[0] * denominator
    numerator[:delay] = 0.0
    return True, a, b, c, eigenvalues, numerator, denominator, u, s, vt


@_jit
def _era_root_std(h, order, delay, covariance, a, b, c, eigenvalues, u, s, vt):
    """``uncertainty.era_root_std``: (ok, poles_std, zeros_std) of the ERA model (A, B, C and A's
    eigenvalues from ``_era``, U S V^T its H(0)) given Cov of h_delay .. h_M. The first-order changes

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
    sqrt_cov = _square_root(covariance)
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
                first_part[p, q] = _dot(d0, k_a[p, q])
                second_part[p, q] = _dot(d1, k_a[p, q])
            big_b[p] = b[p] + _dot(d0, k_b[p])
            big_c[p] = c[p] + _dot(d0[:columns], c_plus_t[p])
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
    poles = _sorted_roots(eigenvalues)
    zeros = np.zeros(0, np.complex128)
    if order > delay:
        zeros, ok = _polynomial_roots(numerator[0, delay:])
        if not ok:
            return False, np.zeros((0, 2)), np.zeros((0, 2))
    return (True, _root_std(_root_derivatives(denominator, poles)),
            _root_std(_root_derivatives(numerator[:, delay:], zeros)))


# --- the solve -------------------------------------------------------------------------------------


@_jit
def _arx_root_std(theta, covariance, order, delay):
    """``propagate`` of the ARX model's poles and zeros (LinearModel of theta = [a | b_d..b_n]):
    (ok, poles_std, zeros_std), roots of each perturbed model matched to the nominal ones."""
    n = order
    denominator = np.empty(n + 1)
    denominator[0] = 1.0
    denominator[1:] = theta[:n]
    poles, ok_p = _polynomial_roots(denominator)
    zeros, ok_z = _polynomial_roots(theta[n:])
    if not (ok_p and ok_z):
        return False, np.zeros((0, 2)), np.zeros((0, 2))
    root = _square_root(covariance)
    dp = np.zeros((root.shape[1], poles.size), np.complex128)
    dz = np.zeros((root.shape[1], zeros.size), np.complex128)
    for i in range(root.shape[1]):
        t = theta + STEP * root[:, i]
        denominator[1:] = t[:n]
        p, ok_p = _polynomial_roots(denominator)
        z, ok_z = _polynomial_roots(t[n:])
        if not (ok_p and ok_z):
            return False, np.zeros((0, 2)), np.zeros((0, 2))
        p, ok_p = _matched(p, poles)
        z, ok_z = _matched(z, zeros)
        if not (ok_p and ok_z):
            return False, np.zeros((0, 2)), np.zeros((0, 2))
        dp[i] = (p - poles) / STEP
        dz[i] = (z - zeros) / STEP
    return True, _root_std(dp), _root_std(dz)


@_jit
def cls_solve(phi_vv, phi_yv, v, y, order, delay, mu, poly, bounds):
    """CLS steps 1 and 2 (``correlation_least_squares_steps``, a polynomial F of degree ``poly``) and,
    with ``bounds``, ``cls_uncertainty``. Returns (status, a, coefficients, numerator, denominator,
    gamma, slope, bounds_status, poles_std, zeros_std, gain_std, map_covariance, blocks): the step-1
    regression's a and input coefficients, the step-1 linear block's polynomials in q^-1 (ARX
    directly, mu-Markov by ERA; not yet scaled by the slope), step 2's gamma_0..gamma_p and
    s = F'(mean v); status / bounds_status FALLBACK where the reference must decide."""
    n, samples = order, v.size
    output_lags, input_lags = _lags(order, delay, mu)
    first = n + mu - 1
    q = poly + 1
    none2 = np.zeros((0, 2))
    failed = (FALLBACK, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), 0.0, FALLBACK,
              none2, none2, 0.0, np.zeros((0, 0)), 0)
    finite = True
    for x in (phi_vv, phi_yv, v, y):
        finite = finite and _all_finite(x)
    if not finite or samples <= first + q or poly < 1 or mu < 1 or delay < 0 or delay > n or n < 1:
        return failed

    # step 1: X theta = z over the correlation lags, with an intercept; X^+ = R^-1 Q^T (X = Q R)
    lags_total = phi_vv.size
    tau_max = (lags_total - 1) // 2
    rows1 = lags_total - first
    p = n + input_lags.size + 1
    if rows1 <= p:
        return failed
    x = np.empty((rows1, p))
    for r in range(rows1):
        k = first + r
        for j in range(n):
            x[r, j] = -phi_yv[k - output_lags[j]]
        for i in range(input_lags.size):
            x[r, n + i] = phi_vv[k - input_lags[i]]
        x[r, p - 1] = 1.0
    qm, rm = np.linalg.qr(x)
    if not _well_conditioned(rm):
        return failed
    q_transposed = np.ascontiguousarray(qm.T)
    theta = _back_substitute(rm, (q_transposed @ np.ascontiguousarray(phi_yv[first:])).reshape(p, 1))[:, 0]
    a = theta[:n].copy()
    coefficients = theta[n : p - 1].copy()

    # the step-1 linear block
    if mu == 1:
        numerator = np.zeros(n + 1)
        numerator[delay:] = coefficients
        denominator = np.empty(n + 1)
        denominator[0] = 1.0
        denominator[1:] = a
        era_a = np.zeros((0, 0))
        era_b = era_c = era_s = np.zeros(0)
        era_roots = np.zeros(0, np.complex128)
        era_u = era_vt = np.zeros((0, 0))
        markov = np.zeros(0)
    else:
        markov = np.zeros(delay + mu)
        markov[delay:] = coefficients[:mu]
        ok, era_a, era_b, era_c, era_roots, numerator, denominator, era_u, era_s, era_vt = _era(markov, order, delay)
        if not ok:
            return failed

    # step 2: gamma of A_hat y = B_hat [1, v, .., v^p] gamma + e, rows from the largest lag on
    taps = np.zeros(first + 1)
    taps[input_lags] = coefficients
    filtered_y = y.copy()  # A_hat(q^-1) y, lag by lag (``regression.filtered_output``)
    for j in range(n):
        _axpy(filtered_y[output_lags[j] :], a[j], y[: samples - output_lags[j]])
    rows2 = samples - first
    target = np.ascontiguousarray(filtered_y[first:])
    regressors = np.zeros((q, rows2))  # B_hat(q^-1) of the basis 1, v, .., v^p (``regression.filtered_basis``)
    regressors[0] = taps.sum()
    power_of_v = v.copy()
    for power in range(1, q):
        if power > 1:
            power_of_v *= v
        _fir(power_of_v, taps, rows2, regressors[power])
    gamma = _householder_solve(regressors, target)
    if gamma.size == 0:
        return failed
    mean = v.sum() / samples
    slope = 0.0
    largest = 1.0
    for power in range(q - 1, 0, -1):  # F'(mean v) by Horner's rule
        slope = slope * mean + power * gamma[power]
    for power in range(q):
        largest = max(largest, abs(gamma[power]))
    if abs(slope) < 1e-12 * largest:
        return failed
    if not bounds:
        return (OK, a, coefficients, numerator, denominator, gamma, slope, FALLBACK, none2, none2, 0.0,
                np.zeros((0, 0)), 0)

    # bounds, step 1: the block sums r_b(tau) of the equation error w times v(k - tau), through X^+
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
        _lagged_dots(w[start : start + length], v, start - lo, r_blocks[b])
    r_blocks /= centres
    g1 = _back_substitute(rm, q_transposed @ r_blocks.T).T * np.sqrt(centres / (blocks * length))  # X^+ r_b
    g1_lin = np.ascontiguousarray(g1[:, : p - 1])
    cov1 = _batch_means_covariance(g1_lin)
    if mu == 1:
        ok, poles_std, zeros_std = _arx_root_std(theta[: p - 1].copy(), cov1, order, delay)
    else:
        taps_cov = np.ascontiguousarray(cov1[n : n + mu, n : n + mu])  # of h_d .. h_(d+mu-1)
        ok, poles_std, zeros_std = _era_root_std(markov, order, delay, taps_cov, era_a, era_b, era_c, era_roots,
                                                 era_u, era_s, era_vt)
    if not ok:
        return (OK, a, coefficients, numerator, denominator, gamma, slope, FALLBACK, none2, none2, 0.0,
                np.zeros((0, 0)), blocks)

    # bounds, step 2: its own influences and step 1's through dgamma/dtheta_1 (normal equations)
    gram = regressors @ regressors.T
    normal_inverse, ok = _inverse(gram)
    if not ok:
        return (OK, a, coefficients, numerator, denominator, gamma, slope, FALLBACK, none2, none2, 0.0,
                np.zeros((0, 0)), blocks)
    gamma_n = normal_inverse @ (regressors @ target)
    residual = target - gamma_n @ regressors
    mapped = np.full(samples, gamma_n[q - 1])  # F_gamma(v) by Horner's rule
    for power in range(q - 2, -1, -1):
        for k in range(samples):
            mapped[k] = mapped[k] * v[k] + gamma_n[power]
    # R^T D over chunks of CHUNK rows: the output lags mu..mu+n-1 and the input lags d..n+mu-1 are consecutive
    # (the constant regressor's: its value times sums of windows)
    lagged_y, lagged_map = np.zeros((q, n)), np.zeros((q, input_lags.size))
    _window_sums(y, first - output_lags[0], rows2, lagged_y[0])
    _window_sums(mapped, first - input_lags[0], rows2, lagged_map[0])
    lagged_y[0] *= regressors[0, 0]
    lagged_map[0] *= regressors[0, 0]
    for begin in range(0, rows2, CHUNK):
        end = min(begin + CHUNK, rows2)
        for e in range(1, q):
            _lagged_dots(regressors[e, begin:end], y, first - output_lags[0] + begin, lagged_y[e])
            _lagged_dots(regressors[e, begin:end], mapped, first - input_lags[0] + begin, lagged_map[e])
    products = np.empty((q, n + input_lags.size))
    products[:, :n], products[:, n:] = lagged_y, -lagged_map
    sensitivity = normal_inverse @ products
    scores = np.zeros((blocks, q))
    for b in range(blocks):
        begin = 0 if b == 0 else tau_max + length * b - first
        end = rows2 if b == blocks - 1 else tau_max + length * (b + 1) - first
        for e in range(q):
            scores[b, e] = _dot(regressors[e, begin:end], residual[begin:end])
    joint = np.empty((blocks, q + 1))
    joint[:, 0] = g1[:, n]
    joint[:, 1:] = scores @ normal_inverse.T + g1_lin @ sensitivity.T

    # the gain h_d s(gamma) and the unit-slope map gamma / s(gamma) (``propagate``)
    powers = np.zeros(q)
    for power in range(1, q):
        powers[power] = power * mean ** (power - 1)
    estimate = np.empty(q + 1)
    estimate[0] = coefficients[0]
    estimate[1:] = gamma_n
    root = _square_root(_batch_means_covariance(joint))
    nominal = _gain_and_map(estimate, powers)
    changes = np.empty((root.shape[1], q + 1))
    for i in range(root.shape[1]):
        changes[i] = (_gain_and_map(estimate + STEP * root[:, i], powers) - nominal) / STEP
    cov = changes.T @ changes
    return (OK, a, coefficients, numerator, denominator, gamma, slope, OK, poles_std, zeros_std,
            np.sqrt(cov[0, 0]), cov[1:, 1:].copy(), blocks)


@_jit
def _gain_and_map(t, powers):
    """[h_d s, gamma / s] of t = [h_d, gamma], s = F'(mean v) = powers . gamma."""
    scale = np.dot(powers, t[1:])
    out = np.empty(t.size)
    out[0] = t[0] * scale
    out[1:] = t[1:] / scale
    return out
