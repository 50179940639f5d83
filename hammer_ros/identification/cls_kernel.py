"""The CLS solve of paper 000 (sec. 3.1) from the correlation functions, with its confidence
bounds, as one numba kernel (``cls_solve``): the same arithmetic as the numpy reference
(``correlation_least_squares.correlation_least_squares_steps`` for the estimate; the bounds, by
``cls_bounds_kernel``, as ``uncertainty.cls_uncertainty``), in loops and a few LAPACK calls instead
of ~150 numpy calls. Equal to the reference to rounding (the tests compare estimates and bounds to
1e-9 relative); its sums run in another order, so the last digits differ.

Covered: a polynomial F (no partition), open loop (no instrument), ARX (mu = 1) and mu-Markov.
Where the reference takes another branch (a nearly rank-deficient regression, an ERA of too low a
rank, an F without slope, non-finite data, a root matching beyond 4 roots) the kernel returns
status FALLBACK and the caller runs the reference, which raises or answers as before.

Imported on the first compiled solve only (``import hammer_ros`` stays light, as
``compiled_loops``); compiled with ``nogil=True`` (solves of several channels may run in threads at
once) and ``cache=True`` (numba's cache beside this file: a process after the first loads the
machine code). numba checks only this file's source before it loads ``cls_solve`` from its cache,
but the machine code holds its callees from ``CALLEE_MODULES`` too; so this file records their
digest (``CALLEE_DIGEST``: a change there must change this file), and while it does not match,
``cls_solve`` compiles without the cache (``test_compiled_cls`` names the digest to write).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numba
import numpy as np

from .cls_bounds_kernel import FALLBACK, OK, cls_bounds, no_bounds
from .cls_numerics import (
    TINY,
    all_finite,
    axpy,
    back_substitute,
    complex_eigenvalues,
    fir,
    householder_solve,
    jit,
    polynomial_from_roots,
    well_conditioned,
)

CALLEE_MODULES = ("cls_bounds_kernel.py", "cls_numerics.py")
CALLEE_DIGEST = "4b37a80a964d56a8abad6d472a1c5528b0ad7da1f5c50a2348c88e076be4262b"


def callee_digest() -> str:
    """sha256 of the sources of CALLEE_MODULES (beside this file)."""
    digest = hashlib.sha256()
    for name in CALLEE_MODULES:
        digest.update((Path(__file__).parent / name).read_bytes())
    return digest.hexdigest()


@jit
def _lags(order, delay, mu):
    """``regression.markov_lags``: output lags mu..mu+n-1, input lags d..d+mu-1 and d+1+mu-1..n+mu-1."""
    output = np.arange(1, order + 1) + mu - 1
    inputs = np.empty(mu + order - delay, np.int64)
    inputs[:mu] = np.arange(delay, delay + mu)
    inputs[mu:] = np.arange(delay + 1, order + 1) + mu - 1
    return output, inputs


# --- ERA (era.py) ---------------------------------------------------------------------------------


@jit
def _hankel(h, rows, columns, offset):
    """H[i, j] = h[offset + i + j]."""
    out = np.empty((rows, columns))
    for i in range(rows):
        for j in range(columns):
            out[i, j] = h[offset + i + j]
    return out


@jit
def _era(h, order, delay):
    """The ERA realisation of ``era.eigensystem_realization`` (default Hankel size) and its transfer
    function (``to_linear_model``): (ok, A, B, C, eigenvalues of A, numerator, denominator, U, S, V^T of H(0))."""
    available = h.size - 1
    rows, columns = (available + 1) // 2, available // 2
    empty, none = np.zeros((0, 0)), np.zeros(0)
    if rows < 1 or columns < 1 or order < 1 or order > min(rows, columns):
        return False, empty, none, none, none.astype(np.complex128), none, none, empty, none, empty
    u, s, vt = np.linalg.svd(_hankel(h, rows, columns, 1))
    if s[order - 1] <= 1e-14 * max(s[0], TINY):
        return False, empty, none, none, none.astype(np.complex128), none, none, empty, none, empty
    root = np.sqrt(s[:order])
    un, vn = np.ascontiguousarray(u[:, :order]), np.ascontiguousarray(vt[:order].T)
    a = (un.T @ _hankel(h, rows, columns, 2) @ vn) / np.outer(root, root)
    b = root * vn[0]
    c = un[0] * root
    eigenvalues = complex_eigenvalues(a)
    denominator = polynomial_from_roots(eigenvalues)
    numerator = polynomial_from_roots(complex_eigenvalues(a - np.outer(b, c))) - denominator + h[0] * denominator
    numerator[:delay] = 0.0
    return True, a, b, c, eigenvalues, numerator, denominator, u, s, vt


# --- the solve -------------------------------------------------------------------------------------


@numba.njit(cache=callee_digest() == CALLEE_DIGEST, nogil=True)
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
        finite = finite and all_finite(x)
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
    if not well_conditioned(rm):
        return failed
    q_transposed = np.ascontiguousarray(qm.T)
    theta = back_substitute(rm, (q_transposed @ np.ascontiguousarray(phi_yv[first:])).reshape(p, 1))[:, 0]
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
        axpy(filtered_y[output_lags[j] :], a[j], y[: samples - output_lags[j]])
    rows2 = samples - first
    target = np.ascontiguousarray(filtered_y[first:])
    regressors = np.zeros((q, rows2))  # B_hat(q^-1) of the basis 1, v, .., v^p (``regression.filtered_basis``)
    regressors[0] = taps.sum()
    power_of_v = v.copy()
    for power in range(1, q):
        if power > 1:
            power_of_v *= v
        fir(power_of_v, taps, rows2, regressors[power])
    gamma = householder_solve(regressors, target)
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
    if bounds:
        bounds_status, poles_std, zeros_std, gain_std, map_covariance, blocks = cls_bounds(
            v, y, order, delay, mu, tau_max, (output_lags, input_lags), (theta, rm, q_transposed),
            (filtered_y, regressors, taps), (markov, era_a, era_b, era_c, era_roots, era_u, era_s, era_vt))
    else:
        bounds_status, poles_std, zeros_std, gain_std, map_covariance, blocks = no_bounds(0)
    return (OK, a, coefficients, numerator, denominator, gamma, slope, bounds_status, poles_std, zeros_std, gain_std,
            map_covariance, blocks)
