"""Sample correlation functions (paper 000 eq. 8; paper 003 eq. 21).

All functions use the estimator of paper 000, Remark 2: from L = N + 2 tau_max + 1 samples,

    phi_xy(tau) = 1/(N+1) sum_{k=tau_max}^{tau_max+N} y(k) x(k - tau),   |tau| <= tau_max,

so that every lag is averaged over the same N + 1 products. The returned array is indexed
by tau + tau_max (tau = -tau_max .. tau_max). The streaming engine reproduces exactly this
estimator on its window.
"""

from __future__ import annotations

import numpy as np


def cross_correlation(x: np.ndarray, y: np.ndarray, tau_max: int) -> np.ndarray:
    """phi_yx(tau) = E{y(k) x(k - tau)} for tau = -tau_max..tau_max (paper 000, eq. 8b)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
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


def auto_correlation(v: np.ndarray, tau_max: int) -> np.ndarray:
    """phi_vv(tau) for tau = -tau_max..tau_max (paper 000, eq. 8a)."""
    return cross_correlation(v, v, tau_max)


def lags(tau_max: int) -> np.ndarray:
    """The lag axis -tau_max..tau_max matching the correlation arrays."""
    return np.arange(-tau_max, tau_max + 1)
