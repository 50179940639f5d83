"""The arithmetic of ``levenberg_marquardt`` as numba kernels: MINPACK's ``enorm``, ``qrfac`` with
pivoting, ``lmpar`` and ``qrsolv`` and lmder's two small sums (the scaled gradient norm, the
predicted reduction), statement for statement in MINPACK's order of operations, so that the results
equal scipy's C MINPACK to the bit (apart from its norm recomputation, ``levenberg_marquardt``'s
docstring). Compiled machine code without fast-math: no reassociation, no fused multiply-adds.
Imported on the first ``levenberg_marquardt`` call; ``cache=True`` (numba's cache beside this file,
whose source numba checks: every kernel is in it), ``nogil=True``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

EPSILON = float(np.finfo(float).eps)
TINY = float(np.finfo(float).tiny)

jit = numba.njit(nogil=True, cache=True)


RDWARF, RGIANT = 3.834e-20, 1.304e19  # MINPACK's enorm: squares of these neither underflow nor overflow


@jit
def _dot(x, z):
    """x . z, summed in order as MINPACK's loops sum."""
    total = 0.0
    for k in range(x.size):
        total += x[k] * z[k]
    return total


@jit
def enorm(x):
    """MINPACK ``enorm``: ||x||, the squares of the small (<= RDWARF) and large (>= RGIANT / n)
    components scaled by their largest, the intermediate ones summed in order."""
    small = intermediate = large = small_max = large_max = 0.0
    giant = RGIANT / x.size
    for k in range(x.size):
        value = abs(x[k])
        if RDWARF < value < giant:
            intermediate += value * value
        elif value > RDWARF:
            if value > large_max:
                large = 1.0 + large * (large_max / value) ** 2
                large_max = value
            else:
                large += (value / large_max) ** 2
        elif value > small_max:
            small = 1.0 + small * (small_max / value) ** 2
            small_max = value
        elif value != 0.0:
            small += (value / small_max) ** 2
    if large != 0.0:
        return large_max * math.sqrt(large + (intermediate / large_max) / large_max)
    if intermediate != 0.0:
        if intermediate >= small_max:
            return math.sqrt(intermediate * (1.0 + (small_max / intermediate) * (small_max * small)))
        return math.sqrt(small_max * ((intermediate / small_max) + (small_max * small)))
    return small_max * math.sqrt(small)


@jit
def gradient_norm(r, pivots, column_norms, qtf, fnorm):
    """lmder's scaled gradient norm: max_j |sum_(i<=j) R[i, j] (Q^T f)_i / ||f|| | / ||J e_pivots[j]||."""
    largest = 0.0
    for j in range(r.shape[0]):
        if column_norms[pivots[j]] != 0.0:
            total = 0.0
            for i in range(j + 1):
                total += r[i, j] * (qtf[i] / fnorm)
            largest = max(largest, abs(total / column_norms[pivots[j]]))
    return largest


@jit
def predicted_norm(r, pivots, p):
    """||R P^T p||, R P^T p accumulated column by column as lmder does."""
    n = r.shape[0]
    out = np.zeros(n)
    for j in range(n):
        step = p[pivots[j]]
        for i in range(j + 1):
            out[i] += r[i, j] * step
    return enorm(out)


@jit
def qr_pivoted(a, f):
    """MINPACK ``qrfac`` with pivoting on J (its columns the rows of ``a``, overwritten) and the first n
    entries of Q^T f: (R (n x n, upper), the pivots (column j of R is J's column pivots[j]), J's
    column norms, Q^T f[:n]). Householder reflections; at each step the remaining column of largest
    norm (norms downdated, recomputed when they lose too much)."""
    n, m = a.shape
    column_norms = np.empty(n)
    for j in range(n):
        column_norms[j] = enorm(a[j])
    norms, original = column_norms.copy(), column_norms.copy()
    pivots = np.arange(n)
    r = np.zeros((n, n))
    for j in range(n):
        k_max = j
        for k in range(j + 1, n):
            if norms[k] > norms[k_max]:
                k_max = k
        if k_max != j:
            for i in range(m):
                a[j, i], a[k_max, i] = a[k_max, i], a[j, i]
            norms[k_max], original[k_max] = norms[j], original[j]
            pivots[j], pivots[k_max] = pivots[k_max], pivots[j]
        v = a[j, j:]
        v_norm = enorm(v)
        if v_norm != 0.0:
            if v[0] < 0.0:
                v_norm = -v_norm
            for i in range(v.size):
                v[i] /= v_norm
            v[0] += 1.0
            for k in range(j + 1, n):
                column = a[k, j:]
                scale = _dot(v, column) / v[0]
                for i in range(v.size):
                    column[i] -= scale * v[i]
                if norms[k] != 0.0:
                    ratio = a[k, j] / norms[k]
                    norms[k] *= math.sqrt(max(0.0, 1.0 - ratio * ratio))
                    if 0.05 * (norms[k] / original[k]) ** 2 <= EPSILON:
                        norms[k] = enorm(a[k, j + 1 :])
                        original[k] = norms[k]
        for i in range(j):
            r[i, j] = a[j, i]
        r[j, j] = -v_norm
    qtf = f.copy()
    for j in range(min(n, m)):
        v = a[j, j:]
        if v[0] != 0.0:
            tail = qtf[j:]
            scale = _dot(v, tail) / v[0]
            for i in range(v.size):
                tail[i] -= scale * v[i]
    return r, pivots, column_norms, qtf[:n].copy()


@jit
def lm_parameter(r, pivots, diag, qtb, delta, par):
    """MINPACK ``lmpar``: (lambda, p) with p solving min ||J p - f||^2 + lambda ||D p||^2 and either
    lambda = 0 with ||D p|| <= 1.1 delta (the Gauss-Newton step fits) or | ||D p|| - delta | <=
    0.1 delta, by Moré's safeguarded Newton iteration on phi(lambda) = ||D p|| - delta (at most 10
    solves ``solve_damped``) from the previous ``par``. J P = Q R."""
    n = r.shape[0]
    singular = n
    for j in range(n):
        if r[j, j] == 0.0:
            singular = j
            break
    w = np.zeros(n)
    w[:singular] = qtb[:singular]
    for j in range(singular - 1, -1, -1):
        w[j] /= r[j, j]
        for i in range(j):
            w[i] -= r[i, j] * w[j]
    step = np.empty(n)
    for j in range(n):
        step[pivots[j]] = w[j]
    scaled = diag * step
    dxnorm = enorm(scaled)
    fp = dxnorm - delta
    if fp <= 0.1 * delta:
        return 0.0, step
    lower = 0.0
    if singular == n:
        for j in range(n):
            w[j] = diag[pivots[j]] * (scaled[pivots[j]] / dxnorm)
        for j in range(n):
            total = 0.0
            for i in range(j):
                total += r[i, j] * w[i]
            w[j] = (w[j] - total) / r[j, j]
        size = enorm(w)
        lower = fp / delta / size / size
    for j in range(n):
        total = 0.0
        for i in range(j + 1):
            total += r[i, j] * qtb[i]
        w[j] = total / diag[pivots[j]]
    gnorm = enorm(w)
    upper = gnorm / delta
    if upper == 0.0:
        upper = TINY / min(delta, 0.1)
    par = min(max(par, lower), upper)
    if par == 0.0:
        par = gnorm / dxnorm
    for iteration in range(1, 11):
        if par == 0.0:
            par = max(TINY, 0.001 * upper)
        step, sdiag, s = solve_damped(r, pivots, math.sqrt(par) * diag, qtb)
        scaled = diag * step
        dxnorm = enorm(scaled)
        previous = fp
        fp = dxnorm - delta
        if abs(fp) <= 0.1 * delta or (lower == 0.0 and previous < 0.0 and fp <= previous) or iteration == 10:
            break
        for j in range(n):
            w[j] = diag[pivots[j]] * (scaled[pivots[j]] / dxnorm)
        for j in range(n):
            w[j] /= sdiag[j]
            for i in range(j + 1, n):
                w[i] -= s[i, j] * w[j]
        size = enorm(w)
        correction = fp / delta / size / size
        if fp > 0.0:
            lower = max(lower, par)
        elif fp < 0.0:
            upper = min(upper, par)
        par = max(lower, par + correction)
    return par, step


@jit
def solve_damped(r, pivots, d, qtb):
    """MINPACK ``qrsolv``: x minimising ||[R; D P] P^T x - [Q^T b; 0]|| given J P = Q R, by Givens
    rotations that turn [R; D P] into [S; 0] (S upper triangular, its diagonal ``sdiag``, S^T in
    the lower triangle of the third result); a singular S gives the least-squares solution with
    its last components 0."""
    n = r.shape[0]
    s = np.zeros((n, n))
    for j in range(n):
        for i in range(j, n):
            s[i, j] = r[j, i]
    z = qtb[:n].copy()
    sdiag = np.zeros(n)
    for j in range(n):
        damping = d[pivots[j]]
        if damping != 0.0:
            sdiag[j:] = 0.0
            sdiag[j] = damping
            extra = 0.0
            for k in range(j, n):
                if sdiag[k] == 0.0:
                    continue
                if abs(s[k, k]) < abs(sdiag[k]):
                    cotangent = s[k, k] / sdiag[k]
                    sine = 0.5 / math.sqrt(0.25 + 0.25 * cotangent * cotangent)
                    cosine = sine * cotangent
                else:
                    tangent = sdiag[k] / s[k, k]
                    cosine = 0.5 / math.sqrt(0.25 + 0.25 * tangent * tangent)
                    sine = cosine * tangent
                s[k, k] = cosine * s[k, k] + sine * sdiag[k]
                rotated = cosine * z[k] + sine * extra
                extra = -sine * z[k] + cosine * extra
                z[k] = rotated
                for i in range(k + 1, n):
                    rotated = cosine * s[i, k] + sine * sdiag[i]
                    sdiag[i] = -sine * s[i, k] + cosine * sdiag[i]
                    s[i, k] = rotated
        sdiag[j] = s[j, j]
    singular = n
    for j in range(n):
        if sdiag[j] == 0.0:
            singular = j
            break
    z[singular:] = 0.0
    for j in range(singular - 1, -1, -1):
        total = 0.0
        for i in range(j + 1, singular):
            total += s[i, j] * z[i]
        z[j] = (z[j] - total) / sdiag[j]
    x = np.empty(n)
    for j in range(n):
        x[pivots[j]] = z[j]
    return x, sdiag, s
