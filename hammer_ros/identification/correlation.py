"""Sample correlation functions (paper 000 eq. 8; paper 003 eq. 21).

All functions use the estimator of paper 000, Remark 2: from L = N + 2 tau_max + 1 samples,

    phi_xy(tau) = 1/(N+1) sum_{k=tau_max}^{tau_max+N} y(k) x(k - tau),   |tau| <= tau_max,

so that every lag is averaged over the same N + 1 products. The returned array is indexed
by tau + tau_max (tau = -tau_max .. tau_max). The streaming engine reproduces exactly this
estimator on its window.
"""

from __future__ import annotations

import numpy as np

from .runs import Runs, several


def cross_correlation(x: np.ndarray, y: np.ndarray, tau_max: int, runs: Runs | None = None) -> np.ndarray:
    """phi_yx(tau) = E{y(k) x(k - tau)} for tau = -tau_max..tau_max (paper 000, eq. 8b).

    With ``runs`` (several experiments concatenated), the products of every run's own centres
    k = start + tau_max .. end - 1 - tau_max are summed and divided by their total count: no
    product pairs samples of two runs; runs shorter than 2 tau_max + 1 add nothing."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    runs = several(runs)
    if runs is not None:
        if x.size != runs.total or y.size != runs.total:
            raise ValueError(f"signals of {x.size} and {y.size} samples for runs of {runs.total}")
        usable = [s for s in runs.slices() if s.stop - s.start > 2 * tau_max]
        if not usable:
            raise ValueError(f"need a run of at least 2 tau_max + 1 = {2 * tau_max + 1} samples")
        counts = [s.stop - s.start - 2 * tau_max for s in usable]
        total = sum(n * cross_correlation(x[s], y[s], tau_max) for n, s in zip(counts, usable))
        return total / sum(counts)
    length = x.size
    if y.size != length:
        raise ValueError(f"signals differ in length ({x.size} vs {y.size})")
    n_products = length - 2 * tau_max
    if tau_max < 0 or n_products < 1:
        raise ValueError(f"need at least 2 tau_max + 1 = {2 * tau_max + 1} samples, got {length}")
    centre = y[tau_max : tau_max + n_products]
    out = np.empty(2 * tau_max + 1)
    for i, tau in enumerate(range(-tau_max, tau_max + 1)):
        out[i] = centre @ x[tau_max - tau : tau_max - tau + n_products]
    return out / n_products


def auto_correlation(v: np.ndarray, tau_max: int, runs: Runs | None = None) -> np.ndarray:
    """phi_vv(tau) for tau = -tau_max..tau_max (paper 000, eq. 8a); ``runs`` as in ``cross_correlation``."""
    return cross_correlation(v, v, tau_max, runs)


def lags(tau_max: int) -> np.ndarray:
    """The lag axis -tau_max..tau_max matching the correlation arrays."""
    return np.arange(-tau_max, tau_max + 1)


def centred_square(x: np.ndarray) -> np.ndarray:
    """w(k) = x'(k)^2 - mean(x'^2) with x' = x - mean(x), means over the whole record: the
    input of the second-order cross-correlation (paper 003, eq. 21)."""
    deviation = np.asarray(x, dtype=float) - np.mean(x)
    square = deviation**2
    return square - square.mean()


def second_order_cross_correlation(x: np.ndarray, y: np.ndarray, tau_max: int, runs: Runs | None = None) -> np.ndarray:
    """phi_xxy'(tau) = E{y'(k) x'^2(k - tau)}, tau = -tau_max..tau_max (paper 003, eq. 21),
    with y' = y - mean(y) and x' = x - mean(x) (the zero-mean Gaussian part of the input).

    Computed as ``cross_correlation(centred_square(x), y', tau_max)``, i.e. with the same
    eq. 8 estimator (N + 1 products per lag). Centring x'^2 changes nothing in expectation
    (E{y'} = 0) and makes auto_correlation(centred_square(x)) = 2 phi_xx^2 (eq. 25), the
    "input" against which the second-order correlation is fitted. ``runs`` as in
    ``cross_correlation`` (the means stay those of the whole record).
    """
    y = np.asarray(y, dtype=float)
    return cross_correlation(centred_square(x), y - y.mean(), tau_max, runs)


def weighted_cross_correlation(x: np.ndarray, y: np.ndarray, tau_max: int, forgetting: float) -> np.ndarray:
    """Exponentially weighted form of eq. 8b, the batch reference of the streaming engine's
    forgetting mode: with the centres k = tau_max .. c (c = L - 1 - tau_max, the newest centre
    whose lags are all available) weighted by lambda^(c - k),

        phi_yx(tau) = sum_k lambda^(c-k) y(k) x(k - tau) / sum_k lambda^(c-k),

    which is ``cross_correlation`` for lambda = 1."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if not 0.0 < forgetting <= 1.0:
        raise ValueError(f"forgetting factor must be in (0, 1], got {forgetting}")
    n_products = x.size - 2 * tau_max
    if y.size != x.size or tau_max < 0 or n_products < 1:
        raise ValueError(f"need two signals of equal length >= 2 tau_max + 1 = {2 * tau_max + 1}")
    weights = forgetting ** np.arange(n_products - 1, -1, -1)
    centre = weights * y[tau_max : tau_max + n_products]
    out = np.array([centre @ x[tau_max - tau : tau_max - tau + n_products] for tau in lags(tau_max)])
    return out / weights.sum()
