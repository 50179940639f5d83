"""Correlation tests of a model's residuals with 95 % bounds that hold for coloured signals.

For two series x, e that are independent of each other, Bartlett's formula gives the
variance of the sample cross-correlation coefficient at any lag (Bartlett 1946; Box &
Jenkins, Time Series Analysis, eq. 11.1.7):

    var r_xe(tau) ~ (1/N) sum_j rho_xx(j) rho_ee(j),

which reduces to 1/N only when one of them is white. For the autocorrelation of e under the
hypothesis that it is a moving average of order tau - 1 (the bounds of an ACF plot):

    var r_ee(tau) ~ (1/N) (1 + 2 sum_{j<tau} rho_ee(j)^2).

The tests (the residual e is the free-run simulation error of the model):

* Billings & Voon (1986), "Correlation based model validity tests for non-linear models",
  Int. J. Control 44(1): phi_ee(tau) = delta(tau), phi_ue(tau) = 0, phi_(u^2)'e(tau) = 0,
  phi_(u^2)'e^2(tau) = 0, phi_e(eu)(tau) = E[e(k) e(k-1-tau) u(k-1-tau)] = 0 (tau >= 0), with
  (u^2)' = u^2 - mean(u^2).
* Billings & Zhu (1994), "Nonlinear model validation using correlation tests", Int. J.
  Control 60(6): the output-based tests phi_(ye)'(e^2)'(tau) = kappa delta(tau) and
  phi_(ye)'(u^2)'(tau) = 0, with (ye)' = y e - mean(y e).

A test fails when the largest normalised correlation |r(tau)| / sigma(tau) over its lags
exceeds the simultaneous 95 % level (Bonferroni over the lags); the per-lag bounds
1.96 sigma(tau) are what the report draws.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from ..identification.correlation import cross_correlation
from ..identification.runs import Runs
from .split import per_run

MAX_LAG = 20


@dataclass(frozen=True)
class Evidence:
    """One line of the contract's ``evidence`` list; ``cause`` is the cause a failure points
    to (None for the generic whiteness/independence tests)."""

    test: str
    value: float
    bound: float
    passed: bool
    cause: str | None = None
    note: str = ""  # advice in plain words (the ``closed_loop`` row: what the feedback means here)

    def to_json(self) -> dict:
        doc = {"test": self.test, "value": float(self.value), "bound": float(self.bound), "passed": bool(self.passed)}
        return doc | ({"note": self.note} if self.note else {})


@dataclass(frozen=True, eq=False)
class CorrelationTest:
    """A correlation function with its per-lag 95 % bounds and the simultaneous verdict."""

    name: str
    lags: np.ndarray
    values: np.ndarray
    bounds: np.ndarray  # 1.96 sigma(tau)
    excluded: np.ndarray  # lags where the hypothesis allows a non-zero value (tau = 0 of delta tests)

    def evidence(self) -> Evidence:
        """value = |r| at the worst lag, bound = the simultaneous 95 % bound at that lag."""
        keep = ~self.excluded
        sigma = self.bounds[keep] / 1.96
        ratio = np.abs(self.values[keep]) / sigma
        worst = int(np.argmax(ratio))
        z = simultaneous_level(int(np.count_nonzero(keep)))
        value, bound = float(np.abs(self.values[keep][worst])), float(z * sigma[worst])
        return Evidence(self.name, value, bound, value <= bound)


def simultaneous_level(count: int, level: float = 0.95) -> float:
    """z such that `count` Gaussian statistics all stay within +-z with probability ~ level."""
    return float(stats.norm.ppf(1.0 - (1.0 - level) / (2.0 * max(count, 1))))


def _standardised(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float) - np.mean(x)
    s = np.std(x)
    return x / s if s > 0 else x


def correlation(x: np.ndarray, e: np.ndarray, max_lag: int, runs: Runs | None = None) -> np.ndarray:
    """r_xe(tau) = corr(e(k), x(k - tau)), tau = -max_lag..max_lag (paper 000's estimator, eq. 8,
    on the standardised signals; ``runs``: products within a run only)."""
    return cross_correlation(_standardised(x), _standardised(e), max_lag, runs)


def autocorrelation_coefficients(x: np.ndarray, max_lag: int, runs: Runs | None = None) -> np.ndarray:
    """rho_xx(0..max_lag), biased estimator (always a valid autocorrelation sequence); with
    ``runs`` the lagged products of every run summed (none across a boundary)."""
    z = _standardised(x)
    n = z.size
    acov = np.zeros(max_lag + 1)
    for part in (runs.split(z) if runs is not None else [z]):
        spectrum = np.fft.rfft(part, 2 * part.size)
        products = np.fft.irfft(np.abs(spectrum) ** 2)[: max_lag + 1]
        acov[: products.size] += products
    acov /= n
    return acov / acov[0] if acov[0] > 0 else acov


def bartlett_cross_sigma(x: np.ndarray, e: np.ndarray, window: int | None = None, runs: Runs | None = None) -> float:
    """sqrt((1/N) sum_{|j|<=M} rho_xx(j) rho_ee(j)): the standard deviation of r_xe(tau) for
    independent x and e (lag-independent); M = ``window`` (default min(N/10, 200))."""
    n = np.size(x)
    m = int(window if window is not None else max(1, min(n // 10, 200)))
    product = autocorrelation_coefficients(x, m, runs) * autocorrelation_coefficients(e, m, runs)
    total = product[0] + 2.0 * np.sum(product[1:])
    return float(np.sqrt(max(total, 0.5) / n))


def bartlett_auto_sigma(rho: np.ndarray, n: int) -> np.ndarray:
    """sigma of r_ee(tau), tau = 1..len(rho)-1, under MA(tau - 1) (Bartlett)."""
    cumulative = np.concatenate([[0.0], np.cumsum(rho[1:-1] ** 2)])
    return np.sqrt((1.0 + 2.0 * cumulative) / n)


def whiteness_test(e: np.ndarray, max_lag: int = MAX_LAG, runs: Runs | None = None) -> CorrelationTest:
    """phi_ee(tau) = delta(tau), tau = 1..max_lag."""
    rho = autocorrelation_coefficients(e, max_lag, runs)
    sigma = bartlett_auto_sigma(rho, np.size(e))
    return CorrelationTest("phi_ee (whiteness)", np.arange(1, max_lag + 1), rho[1:], 1.96 * sigma,
                           np.zeros(max_lag, dtype=bool))


def cross_test(name: str, x: np.ndarray, e: np.ndarray, max_lag: int = MAX_LAG, one_sided: bool = False,
               delta: bool = False, runs: Runs | None = None) -> CorrelationTest:
    """r_xe(tau) against 0 with Bartlett bounds; ``one_sided`` keeps tau >= 0 (x leading e),
    ``delta`` allows a non-zero value at tau = 0."""
    r = correlation(x, e, max_lag, runs)
    lags = np.arange(-max_lag, max_lag + 1)
    if one_sided:
        r, lags = r[max_lag:], lags[max_lag:]
    sigma = bartlett_cross_sigma(x, e, runs=runs)
    excluded = (lags == 0) if delta else np.zeros(r.size, bool)
    return CorrelationTest(name, lags, r, np.full(r.size, 1.96 * sigma), excluded)


def residual_tests(u: np.ndarray, y: np.ndarray, e: np.ndarray, max_lag: int = MAX_LAG,
                   runs: Runs | None = None) -> list[CorrelationTest]:
    """The Billings-Voon and Billings-Zhu tests of the residual e of a model of (u, y); ``runs``:
    separate experiments, no lagged product across a boundary (runs shorter than 2 max_lag + 1
    samples add nothing to the cross-correlations)."""
    u, y, e = (np.asarray(s, dtype=float) for s in (u, y, e))
    if runs is not None and runs.count > 1:
        long_runs = [i for i, n in enumerate(runs.lengths) if n > 2 * max_lag]
        if not long_runs:
            runs = None  # no run holds the lags: the record as one
        elif len(long_runs) < runs.count:
            keep, runs = runs.select(long_runs)
            u, y, e = u[keep], y[keep], e[keep]
    u2 = u**2 - np.mean(u**2)
    e2 = e**2 - np.mean(e**2)
    ye = y * e - np.mean(y * e)
    eu = per_run(lambda x: np.concatenate([[0.0], x[:-1]]), e * u, runs)  # e(k - 1 - tau) u(k - 1 - tau) at lag tau
    return [
        whiteness_test(e, max_lag, runs),
        cross_test("phi_ue", u, e, max_lag, runs=runs),
        cross_test("phi_(u^2)'e", u2, e, max_lag, runs=runs),
        cross_test("phi_(u^2)'e^2", u2, e2, max_lag, runs=runs),
        cross_test("phi_e(eu)", eu, e, max_lag, one_sided=True, runs=runs),
        cross_test("phi_(ye)'(e^2)' (Billings-Zhu)", ye, e2, max_lag, delta=True, runs=runs),
        cross_test("phi_(ye)'(u^2)' (Billings-Zhu)", u2, ye, max_lag, runs=runs),
    ]
