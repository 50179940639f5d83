"""Levenberg-Marquardt least squares with a forward-difference Jacobian: MINPACK's ``lmder``
(Moré, Garbow & Hillstrom, User Guide for MINPACK-1, ANL-80-74, 1980; the algorithm of Moré,
"The Levenberg-Marquardt algorithm: implementation and theory", LNM 630, 1978) fed the Jacobian
that ``scipy.optimize.least_squares(method="lm")`` forms, i.e. that call's algorithm.

Why not that call: scipy (1.15 on) runs a C translation of MINPACK whose ``qrfac``, when it
recomputes a pivot column's norm, sums m - j entries from row j + 1: one past the column, and
past the whole array for the last column. What lies there depends on the process's memory, so
the steps from the same start and the same residuals differed by ~1e-9 from one process to the
next, and a non-convex simulation-error fit ended in another minimum now and then: the diagnosis
of a record was not the same twice (docs/notes/diagnosis-measurements.md). Here the same
arithmetic in the same order, with that norm over the column's own m - j - 1 entries (as the
Fortran): the Jacobian columns (f(x + h e_j) - f(x)) / h, h = sqrt(eps) sign(x_j) max(1, |x_j|)
recomputed as (x_j + h) - x_j; the scaling of ``x_scale="jac"``; step bound factor 100;
``max_evaluations`` counting the start and the trial points (scipy's ``max_nfev``); ``enorm``,
``qrfac``, ``lmpar`` and ``qrsolv`` compiled (``levenberg_marquardt_kernel``). Its results equal
scipy's bit for bit where scipy's norm recomputation does not occur (``test_levenberg_marquardt``),
and are the same in every process.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

EPSILON = float(np.finfo(float).eps)
STEP_BOUND_FACTOR = 100.0  # MINPACK's ``factor``: the first step bound is 100 x ||D x||
ACCEPT_RATIO = 1e-4  # a step is taken when it achieves this share of its predicted reduction


@dataclass(frozen=True)
class LeastSquaresSolution:
    """The point reached, its residuals and cost 0.5 ||f||^2, the residual evaluations made
    (the Jacobian's included) and MINPACK's ``info`` (1-3: converged, 4: gradient, 5: evaluations
    used up, 6-8: tolerances too small)."""

    x: np.ndarray
    residuals: np.ndarray
    cost: float
    evaluations: int  # at the start and the trial points (what ``max_evaluations`` bounds)
    jacobians: int  # forward-difference Jacobians formed (n evaluations each)
    status: int


def levenberg_marquardt(residuals: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, max_evaluations: int,
                        ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8) -> LeastSquaresSolution:
    """x minimising ||residuals(x)||^2 from ``x0``: MINPACK ``lmder`` with mode 1 (variables scaled by
    the Jacobian's column norms, the largest seen so far), as ``least_squares(method="lm",
    x_scale="jac", max_nfev=max_evaluations)`` (module docstring). Each outer iteration forms J by forward differences
    and its QR factorisation with column pivoting (``levenberg_marquardt_kernel.qr_pivoted``); each inner one takes the
    Levenberg-Marquardt parameter for the trust region ||D p|| <= delta (``lm_parameter``), tries
    x + p and updates delta from the ratio of actual to predicted reduction. Stops (``status``) when
    both reductions are below ``ftol`` (1), delta is below ``xtol`` ||D x|| (2), the scaled gradient
    is below ``gtol`` (4) or ``max_evaluations`` are used (5)."""
    from . import levenberg_marquardt_kernel as kernel

    x = np.array(x0, dtype=float)
    n = x.size
    f = np.asarray(residuals(x.copy()), dtype=float)
    evaluations, jacobians = 1, 0
    if n == 0 or f.size < n or max_evaluations <= 0:
        raise ValueError(f"levenberg_marquardt: {f.size} residuals for {n} variables, {max_evaluations} evaluations")
    fnorm = kernel.enorm(f)
    step = math.sqrt(EPSILON)
    diag = np.zeros(n)
    delta = xnorm = par = 0.0
    first = True
    status = 0
    while status == 0:
        jacobian = np.empty((n, f.size))  # column j of J in row j
        for j in range(n):
            shifted = x.copy()
            shifted[j] = x[j] + (step if x[j] >= 0.0 else -step) * max(1.0, abs(x[j]))
            jacobian[j] = (np.asarray(residuals(shifted), dtype=float) - f) / (shifted[j] - x[j])
        jacobians += 1
        r, pivots, column_norms, qtf = kernel.qr_pivoted(jacobian, f)
        if first:
            diag = np.where(column_norms == 0.0, 1.0, column_norms)
            xnorm = kernel.enorm(diag * x)
            delta = STEP_BOUND_FACTOR * xnorm or STEP_BOUND_FACTOR
        gnorm = kernel.gradient_norm(r, pivots, column_norms, qtf, fnorm) if fnorm != 0.0 else 0.0
        if gnorm <= gtol:
            status = 4
            break
        diag = np.maximum(diag, column_norms)
        while True:
            par, p = kernel.lm_parameter(r, pivots, diag, qtf, delta, par)
            p = -p
            trial = x + p
            pnorm = kernel.enorm(diag * p)
            if first:
                delta = min(delta, pnorm)
            f_trial = np.asarray(residuals(trial.copy()), dtype=float)
            evaluations += 1
            fnorm_trial = kernel.enorm(f_trial)
            actual = 1.0 - (fnorm_trial / fnorm) ** 2 if 0.1 * fnorm_trial < fnorm else -1.0
            temp1 = kernel.predicted_norm(r, pivots, p) / fnorm
            temp2 = math.sqrt(par) * pnorm / fnorm
            predicted = temp1 * temp1 + temp2 * temp2 / 0.5
            derivative = -(temp1 * temp1 + temp2 * temp2)
            ratio = actual / predicted if predicted != 0.0 else 0.0
            if ratio <= 0.25:
                temp = 0.5 if actual >= 0.0 else 0.5 * derivative / (derivative + 0.5 * actual)
                if 0.1 * fnorm_trial >= fnorm or temp < 0.1:
                    temp = 0.1
                delta = temp * min(delta, pnorm / 0.1)
                par /= temp
            elif par == 0.0 or ratio >= 0.75:
                delta = pnorm / 0.5
                par *= 0.5
            if ratio >= ACCEPT_RATIO:
                x, f, fnorm = trial, f_trial, fnorm_trial
                xnorm = kernel.enorm(diag * x)
                first = False
            reduced = abs(actual) <= ftol and predicted <= ftol and 0.5 * ratio <= 1.0
            if reduced or delta <= xtol * xnorm:
                status = 1 if not delta <= xtol * xnorm else (3 if reduced else 2)
            elif evaluations >= max_evaluations:
                status = 5
            elif abs(actual) <= EPSILON and predicted <= EPSILON and 0.5 * ratio <= 1.0:
                status = 6
            elif delta <= EPSILON * xnorm:
                status = 7
            elif gnorm <= EPSILON:
                status = 8
            if status or ratio >= ACCEPT_RATIO:
                break
    return LeastSquaresSolution(x, f, 0.5 * float(np.dot(f, f)), evaluations, jacobians, status)
