"""The numba building blocks of the compiled CLS solve (``cls_kernel``) and its bounds
(``cls_bounds_kernel``): the long loops over a record, small dense linear algebra (back
substitution, Householder least squares, Gauss-Jordan inverse, Cholesky, the covariance square
root) and polynomial roots, each the arithmetic of its numpy counterpart in ``regression``,
``uncertainty`` and ``linear``.

Compiled without numba's cache: their machine code is linked into the cached ``cls_solve``
(``cls_kernel`` explains how its cache follows changes here).
"""

from __future__ import annotations

import numba
import numpy as np

from .regression import QR_RANK_TOLERANCE
from .uncertainty import RANK_TOLERANCE

TINY = np.finfo(np.float64).tiny

jit = numba.njit(nogil=True)

# --- the long loops: each a whole function (not a call per sum), their sums reassociated so that the
# compiler vectorises them (NaN and inf kept)

CHUNK = 512  # samples per pass of the long loops: their operands stay in the L1 cache across the taps / lags
fast = numba.njit(nogil=True, fastmath={"reassoc", "contract"})


@jit
def axpy(out, alpha, x):
    """out += alpha x, element by element (out and x of one length)."""
    for k in range(out.size):
        out[k] += alpha * x[k]


@fast
def dot(x, z):
    """x . z."""
    total = 0.0
    for k in range(x.size):
        total += x[k] * z[k]
    return total


@fast
def lagged_dots(x, z, start, out):
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


@fast
def all_finite(x):
    """No NaN or inf in x (x * 0 is NaN for both)."""
    total = 0.0
    for k in range(x.size):
        total += x[k] * 0.0
    return total == 0.0


@jit
def window_sums(z, start, length, out):
    """out[t] = sum_i z[start - t + i], i < length, for t < out.size: one window summed, then moved."""
    total = 0.0
    for i in range(length):
        total += z[start + i]
    out[0] = total
    for t in range(1, out.size):
        total += z[start - t] - z[start - t + length]
        out[t] = total


@fast
def fir(x, taps, rows, out):
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


@jit
def back_substitute(r, rhs):
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


@jit
def well_conditioned(r):
    """``regression.least_squares_qr``'s check: min |r_ii| > QR_RANK_TOLERANCE max |r_jj| (finite)."""
    diagonal = np.abs(np.diag(r))
    return diagonal.min() > QR_RANK_TOLERANCE * diagonal.max()


@jit
def householder_solve(columns, target):
    """theta minimising ||target - A theta|| with A's columns the rows of ``columns`` (q x N), by
    Householder QR of [A | target] (``least_squares_qr``); an empty array when R fails its rank check."""
    q, rows = columns.shape
    m = np.empty((q + 1, rows))
    m[:q] = columns
    m[q] = target
    r = np.zeros((q, q))
    for j in range(q):
        x = m[j, j:]
        norm = np.sqrt(dot(x, x))
        alpha = -norm if x[0] >= 0.0 else norm
        x[0] -= alpha  # x is now the reflector's vector v; H = I - 2 v v^T / v^T v
        beta = dot(x, x)
        for c in range(j + 1, q + 1):
            factor = 2.0 * dot(x, m[c, j:]) / beta if beta > 0.0 else 0.0
            axpy(m[c, j:], -factor, x)
        r[j, j] = alpha
        for c in range(j + 1, q):
            r[j, c] = m[c, j]
    if not well_conditioned(r):
        return np.zeros(0)
    rhs = np.empty((q, 1))
    rhs[:, 0] = m[q, :q]
    return back_substitute(r, rhs)[:, 0]


@jit
def inverse(a):
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


@jit
def cholesky(a):
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


@jit
def square_root(covariance):
    """``uncertainty.square_root``: L (p x r), L L^T = Cov, Cholesky or the eigendecomposition's."""
    symmetric = (covariance + covariance.T) / 2.0
    lower, ok = cholesky(symmetric)
    if ok:
        return lower
    w, vectors = np.linalg.eigh(symmetric)
    largest = max(w.max(), 0.0)
    keep = w > RANK_TOLERANCE * max(largest, TINY)
    return vectors[:, keep] * np.sqrt(w[keep])


@jit
def batch_means_covariance(g):
    """``uncertainty.batch_means_covariance``: B/(B-1) sum_b (g_b - mean)(g_b - mean)^T."""
    blocks = g.shape[0]
    centred = g - (g.sum(axis=0) / blocks)
    return blocks / (blocks - 1) * (centred.T @ centred)

# --- roots -----------------------------------------------------------------------------------------


@jit
def complex_eigenvalues(matrix):
    """The eigenvalues of a real square matrix, complex."""
    return np.linalg.eigvals(matrix.astype(np.complex128))


@jit
def sorted_roots(roots):
    """``linear.sorted_roots``: imaginary parts below 1e-12 set to 0, ordered by (real, imaginary), stable."""
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


@jit
def polynomial_roots(coefficients):
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
    return sorted_roots(complex_eigenvalues(companion)), True


@jit
def polynomial_from_roots(roots):
    """``linear.characteristic_polynomial``'s product of z - lambda over the roots (descending powers, real part)."""
    coefficients = np.zeros(roots.size + 1, np.complex128)
    coefficients[0] = 1.0
    for k in range(1, roots.size + 1):
        root = roots[k - 1]
        for i in range(k, 0, -1):
            coefficients[i] -= root * coefficients[i - 1]
    return coefficients.real.copy()

