"""The feedback test: does the input depend on past output, i.e. was the record taken in closed
loop? (``diagnose`` evidence row ``closed_loop``.)

In open loop the input is independent of the noise, so a model's residual e(k) (which holds the
noise) is uncorrelated with every *future* input u(k + tau), tau >= 1, whatever the model error
(Ljung, System Identification, 2nd ed., sec. 16.6: "the cross-correlation between residuals and
inputs for negative lags [...] indicates output feedback"; MATLAB's ``feedback`` and ``resid``).
A coloured input would correlate with e through its own past; so the input is first
prewhitened by a least-squares AR(``AR_ORDER``) fit, and e is correlated with the input's
innovations nu(k) = A_u(q) u(k): in open loop nu(k + tau) is a new, independent part of the
input, white, so the sample correlation coefficient

    r(tau) = sum_k e'(k) nu'(k + tau) / sqrt(sum e'^2 sum nu'^2),   tau = 1..MAX_LAG

(primes: means removed) has variance 1/N at every lag (Bartlett's formula with rho_nunu = delta,
``residual_tests``), for a coloured e too. The bound uses Bartlett's formula with the sample
autocorrelations of nu and e all the same (``bartlett_cross_sigma``): an input that is not a
linear random process (a multisine: its AR innovations keep its lines) leaves nu coloured, and
the bound widens with it. And the residual's part that the present and past input explain
linearly (``causal_projection`` on u(k) .. u(k - INPUT_LAGS): a linear model error, and for a
periodic input, whose future is a linear function of its past, everything at its lines) is
removed first: in open loop what is left is orthogonal to the input's past and so to the
innovations of a random input and to the whole of a periodic one; in closed loop the noise is
left, and the controller brings it into the future input. In closed loop u(k + tau) = K(r - y)(k + tau) carries
the noise of e(k) back (directly, and through the noise's colour): r(tau) is far outside its
bound. The test fails when max |r(tau)| exceeds the simultaneous 95 % level over the lags
(Bonferroni, ``simultaneous_level``); value = that |r|, bound = the level / sqrt(N).
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from ..identification.instrumental import causal_projection
from ..identification.regression import lagged_columns, solve_least_squares
from ..identification.runs import Runs, per_run, several
from ..identification.trust import ModelWarning, closed_loop_warning, is_trajectory
from .residual_tests import MAX_LAG, Evidence, bartlett_cross_sigma, simultaneous_level

AR_ORDER = 10
INPUT_LAGS = 60  # the residual's part explained by u(k) .. u(k - 60) is removed first
TEST_NAME = "closed_loop"
WARNING = "the excitation depends on the response: closed loop; estimates without a reference are biased"
REFERENCE_NOTE = ("the reference was used: the baseline and the extensions are estimated and judged on the "
                  "reference's part of the input (the two-stage method), which the feedback does not bias")


def innovations(u: np.ndarray, order: int = AR_ORDER, runs: Runs | None = None) -> np.ndarray:
    """nu(k) = u'(k) + sum_j a_j u'(k - j), the residual of the least-squares AR(order) fit of
    u' = u - mean(u) (zero before the record), i.e. u prewhitened. With ``runs``: u' = u less its
    run's mean, one AR fit to the rows of every run whose lags stay in the run, and nu of every
    run without its first ``order`` samples (``runs.rows(order)``), concatenated."""
    runs = several(runs)
    u = _centred(u, runs)
    rows = np.arange(order, u.size) if runs is None else runs.rows(order)
    a = solve_least_squares(-lagged_columns(u, range(1, order + 1), rows), u[rows])
    if not np.all(np.isfinite(a)):
        return u if runs is None else u[rows]
    return per_run(lambda part: signal.lfilter(np.concatenate([[1.0], a]), [1.0], part), u, runs)[rows]


def _centred(x: np.ndarray, runs: Runs | None) -> np.ndarray:
    """x less its mean, or less every run's own mean (``runs``: each at its own operating point)."""
    return per_run(lambda part: part - np.mean(part), np.asarray(x, dtype=float), runs)


def future_input_correlation(u: np.ndarray, residual: np.ndarray, max_lag: int = MAX_LAG,
                             runs: Runs | None = None) -> tuple[np.ndarray, float]:
    """(r(tau) of the module docstring for tau = 1..max_lag: the residual against the input's
    innovations tau samples later, its standard deviation under independence). With ``runs`` the
    products e(k) nu(k + tau) are summed over the pairs within one run (no prewhitening filter,
    projection lag or product reaches into another run)."""
    runs = several(runs)
    nu = innovations(u, runs=runs)
    e = np.asarray(residual, dtype=float)
    e = e - causal_projection(e, u, INPUT_LAGS, runs)
    kept = None if runs is None else Runs.from_lengths(runs.lengths - AR_ORDER)
    e = e[-nu.size:] if runs is None else e[runs.rows(AR_ORDER)]
    e, nu = _centred(e, kept), _centred(nu, kept)
    scale = np.sqrt((e @ e) * (nu @ nu))
    if scale == 0.0:
        return np.zeros(max_lag), 1.0
    pieces = [(e, nu)] if kept is None else list(zip(kept.split(e), kept.split(nu)))
    r = np.array([sum(a[: a.size - tau] @ b[tau:] for a, b in pieces) for tau in range(1, max_lag + 1)]) / scale
    return r, bartlett_cross_sigma(nu, e, runs=kept)


def closed_loop_evidence(u: np.ndarray, residual: np.ndarray, max_lag: int = MAX_LAG,
                         reference: bool = False, runs: Runs | None = None) -> Evidence:
    """The ``closed_loop`` evidence row of ``diagnose`` for the measured input ``u`` and a model's
    residual (``passed`` False: the input depends on past residuals, a closed loop); its note says
    what that means for the estimates (``reference``: the diagnosis used one; ``runs``: the runs of
    u, ``future_input_correlation``)."""
    r, sigma = future_input_correlation(u, residual, max_lag, runs)
    value, bound = float(np.max(np.abs(r))), simultaneous_level(max_lag) * sigma
    note = REFERENCE_NOTE if reference else ("" if value <= bound else WARNING)
    return Evidence(TEST_NAME, value, bound, value <= bound, note=note)


def closed_loop_warnings(v: np.ndarray, residual: np.ndarray, runs: Runs | None = None) -> tuple[ModelWarning, ...]:
    """``closed_loop`` (``identification.trust``) when ``closed_loop_evidence`` fails on a model's
    free-run residual (``runs``: within each run). Not for short records, nor for a trajectory
    (``trust.is_trajectory``): the test prewhitens the input as a random process, and a planned
    motion's future follows from its past, so a model error alone would fail it."""
    v, residual = np.asarray(v, dtype=float), np.asarray(residual, dtype=float)
    if v.size < 200 or not np.all(np.isfinite(residual)) or is_trajectory(v):
        return ()
    with np.errstate(all="ignore"):
        evidence = closed_loop_evidence(v, residual, runs=runs)
    return () if evidence.passed else (closed_loop_warning(evidence.value, evidence.bound),)
