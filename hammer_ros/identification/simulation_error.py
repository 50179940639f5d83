"""Simulation-error (output-error) refinement shared by the baseline and every extension.

The equation-error least squares of the papers (CLS, NLS, PLLS, Billings-Fakhouri) are
consistent only for noise entering like the equation error; with measurement noise on y the
free-run simulation they produce is biased. The diagnosis compares models by their free-run
simulation on validation data, so every model is refined on the same criterion on the
estimation data:

    theta_hat = argmin_theta sum_k (y(k) - y_sim(k; theta))^2,

started from the papers' estimate (Levenberg-Marquardt, finite-difference Jacobian:
``levenberg_marquardt``, the same in every process).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy import signal

from .levenberg_marquardt import levenberg_marquardt

Simulator = Callable[[np.ndarray], np.ndarray]


def steady_state_filter(b: np.ndarray, a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """B(q^-1)/A(q^-1) applied to x from the steady state of the constant input x(0) (the
    record starts at rest at its first input value, not at zero); zero state when the block
    has no finite static gain (integrator).

    With a_0 = 1, the transposed direct form II state of ``lfilter`` at rest with unit input
    and output g = B(1)/A(1) is z_i = sum_{j>i} (b_j - a_j g), i = 0..n-1.
    """
    x = np.asarray(x, dtype=float)
    b, a = np.asarray(b, dtype=float), np.asarray(a, dtype=float)
    if a.size != b.size:
        length = max(a.size, b.size)
        b, a = (np.concatenate([c, np.zeros(length - c.size)]) for c in (b, a))
    if x.size == 0 or a.size == 1 or abs(a.sum()) < 1e-9 * np.abs(a).sum():
        return signal.lfilter(b, a, x)
    gain = b.sum() / a.sum()
    zi = np.cumsum((b[1:] - a[1:] * gain)[::-1])[::-1] * x[0]
    return signal.lfilter(b, a, x, zi=zi)[0]


def preroll_simulate(simulate: Simulator, v: np.ndarray, length: int) -> np.ndarray:
    """simulate(v) started from rest at v(0): ``length`` samples of the constant v(0) are
    simulated first and dropped (for structures without a closed-form steady state, e.g. a
    feedback loop or an operator with memory)."""
    v = np.asarray(v, dtype=float)
    if length <= 0 or v.size == 0:
        return simulate(v)
    return simulate(np.concatenate([np.full(length, v[0]), v]))[length:]


def settling_samples(poles: np.ndarray, cap: int = 2000) -> int:
    """Samples for the slowest pole to decay to 0.1 % (at least 20, at most ``cap``)."""
    radius = float(np.max(np.abs(poles))) if np.size(poles) else 0.0
    if radius <= 1e-3:
        return 20
    if radius >= 1.0:
        return cap
    return int(min(cap, max(20, np.ceil(np.log(1e-3) / np.log(radius)))))


def stabilised_denominator(a: np.ndarray, margin: float = 0.999) -> np.ndarray:
    """[1, a_1..a_n] with every root outside radius ``margin`` reflected inside (1 / conj)."""
    a = np.asarray(a, dtype=float)
    if a.size <= 1:
        return a
    roots = np.roots(a)
    outside = np.abs(roots) >= margin
    if not np.any(outside):
        return a
    roots = np.where(outside, 1.0 / np.conj(roots), roots)
    roots = np.where(np.abs(roots) >= margin, roots / np.abs(roots) * margin, roots)
    return np.real(np.poly(roots))


def refine(simulate: Callable[[np.ndarray], np.ndarray], theta0: np.ndarray, y: np.ndarray,
           max_iterations: int = 30, skip: int = 0) -> np.ndarray:
    """theta minimising ||y - simulate(theta)||^2 over samples ``skip``.. (``levenberg_marquardt`` from
    theta0, at most ``max_iterations`` trial points).

    Non-finite or exploding simulations (an unstable intermediate model) are clipped to a
    bound far outside the data, which the LM step control rejects. Returns theta0 when the
    refinement does not lower the cost.
    """
    y = np.asarray(y, dtype=float)[skip:]
    limit = 1e3 * (float(np.std(y)) + float(np.max(np.abs(y))) + 1e-12)

    def residuals(theta: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            r = np.asarray(simulate(theta), dtype=float)[skip:] - y
            if np.max(np.abs(r)) < limit:  # also False for nan
                return r
        return np.clip(np.nan_to_num(r, nan=limit, posinf=limit, neginf=-limit), -limit, limit)

    theta0 = np.asarray(theta0, dtype=float)
    start = float(np.sum(residuals(theta0) ** 2))
    if theta0.size == 0 or theta0.size > y.size:
        return theta0
    try:
        solution = levenberg_marquardt(residuals, theta0, max_iterations, ftol=1e-6, xtol=1e-6)
    except (ValueError, np.linalg.LinAlgError):
        return theta0
    return solution.x if 2.0 * solution.cost < start else theta0


def refine_starts(starts: Sequence[tuple[Callable[[np.ndarray], np.ndarray], np.ndarray]], y: np.ndarray,
                  deterministic: int, screened: int, screen_iterations: int, kept: int,
                  iterations: int) -> list[tuple[int, np.ndarray, float]]:
    """The refined starts of a non-convex simulation-error fit, best first: ``starts`` are
    (simulate, theta0) pairs; the first ``deterministic`` and the others with the smallest error
    at their start (``screened`` in all) are refined ``screen_iterations`` LM evaluations
    (``refine``), the ``kept`` best of those to ``iterations``. Returns (index of the start,
    theta, sum of squared errors) of those refined to the end whose error is finite (none when
    every start diverges)."""
    y = np.asarray(y, dtype=float)

    def cost(i: int, theta: np.ndarray) -> float:
        with np.errstate(all="ignore"):
            c = float(np.sum((np.asarray(starts[i][0](theta), dtype=float) - y) ** 2))
        return c if np.isfinite(c) else np.inf

    def fit(i: int, theta: np.ndarray, count: int) -> tuple[int, np.ndarray, float]:
        theta = refine(starts[i][0], theta, y, count)
        return i, theta, cost(i, theta)

    ranked = sorted(range(deterministic, len(starts)), key=lambda i: cost(i, starts[i][1]))
    chosen = list(range(min(deterministic, len(starts)))) + ranked[: max(screened - deterministic, 0)]
    screened_fits = sorted((fit(i, starts[i][1], screen_iterations) for i in chosen), key=lambda f: f[2])
    finished = [fit(i, theta, iterations) for i, theta, c in screened_fits[:kept] if np.isfinite(c)]
    return sorted((f for f in finished if np.isfinite(f[2])), key=lambda f: f[2])
