"""Instrumental variables from an external reference: identification in closed loop.

In a loop u = K(q)(r - y), y = G F[u] + w, the input u carries the noise w fed back through the
controller, so every estimator that regresses y on u (CLS's correlations with u, the PLLS and
CLS-step-2 least squares) is biased: the equation error is correlated with the regressors.
The reference r is independent of w. Our reading, after Forssell and Ljung ("Closed-loop
identification revisited", Automatica 35, 1999: the indirect / two-stage "projection" methods,
sec. 5-6, and the instrumental-variable method, sec. 4.3) and Laurain, Gilson and Garnier
(CDC 2009, refined instrumental variables for Hammerstein models in closed loop: instruments
built from the reference, the noise-free signals simulated through a first estimate):

* the correlation step of CLS correlates with r instead of u (phi_ur, phi_yr for phi_uu,
  phi_yu, paper 000 eq. 7 with r as the second signal; Bussgang's separability for the
  jointly Gaussian pair (u, r): E{F(u(k)) r(k - tau)} = C_F phi_ur(tau));
* every least-squares step Z^T (target - Phi theta) = 0 becomes the square IV system with
  instruments Z built like Phi from noise-free signals (``solve_instrumental``): the input part
  from u_r, the part of u the reference explains (``reference_part``: the least-squares
  projection of u on r(k), ..., r(k - REFERENCE_LAGS), the first stage of the two-stage method),
  the output lags from y_r, the output of the first IV estimate simulated on u_r (refined IV,
  Laurain et al. sec. 4; the first pass uses the projection of y on r);
* the simulation-error refinement (``--refine``) runs on u_r (``refinement_input``).

Any function of r is uncorrelated with w, so the IV estimate is consistent whatever the
colour of w (also in open loop, where PLLS's equation error is coloured too).
"""

from __future__ import annotations

import numpy as np

from ..errors import IdentificationError, UsageError
from .regression import lagged_columns, solve_least_squares
from .runs import Runs, several

REFERENCE_LAGS = 60  # r(k) .. r(k - 60): the loop's response to r has decayed (poles |z| < 0.92)


def check_reference(reference: np.ndarray | None, length: int) -> np.ndarray | None:
    """The reference as a float array of the record's length (None stays None)."""
    if reference is None:
        return None
    reference = np.asarray(reference, dtype=float).ravel()
    if reference.size != length:
        raise UsageError(f"--reference: {reference.size} samples for a record of {length}")
    if not np.all(np.isfinite(reference)) or np.std(reference) == 0.0:
        raise UsageError("--reference: the reference is constant or not finite; it cannot be an instrument")
    return reference


def projection_columns(signal: np.ndarray, lags: int, runs: Runs | None = None) -> np.ndarray:
    """[1, signal(k), ..., signal(k - lags)] per sample (zero before the record, or before each of ``runs``)."""
    signal = np.asarray(signal, dtype=float)
    if several(runs) is not None:
        return np.concatenate([projection_columns(part, lags) for part in runs.split(signal)])
    padded = np.concatenate([np.zeros(lags), signal])
    rows = np.arange(signal.size) + lags
    return np.column_stack([np.ones(signal.size), lagged_columns(padded, range(lags + 1), rows)])


def projection_coefficients(x: np.ndarray, signal: np.ndarray, lags: int, runs: Runs | None = None) -> np.ndarray:
    """[c, s_0, ..., s_lags] of the least-squares fit of x by ``projection_columns(signal, lags, runs)``."""
    return solve_least_squares(projection_columns(signal, lags, runs), np.asarray(x, dtype=float))


def causal_projection(x: np.ndarray, signal: np.ndarray, lags: int, runs: Runs | None = None) -> np.ndarray:
    """c + sum_{i=0}^{lags} s_i signal(k - i): the least-squares projection of x on the present
    and past of ``signal`` (zero before the record, or before each of ``runs``: one projection
    fitted to all runs, no lag reaching into the previous run)."""
    columns = projection_columns(signal, lags, runs)
    return columns @ solve_least_squares(columns, np.asarray(x, dtype=float))


def reference_part(x: np.ndarray, reference: np.ndarray, lags: int = REFERENCE_LAGS,
                   runs: Runs | None = None) -> np.ndarray:
    """x_r, the ``causal_projection`` of x on the reference: the part of x the present and past
    reference explain, uncorrelated with the noise (the first stage of the two-stage method,
    Forssell and Ljung 1999 sec. 6.2); with ``runs`` the reference's past stops at each run's start."""
    return causal_projection(x, reference, lags, runs)


def refinement_input(v: np.ndarray, reference: np.ndarray | None, runs: Runs | None = None) -> np.ndarray:
    """The input the simulation-error refinement runs on: v in open loop; with a reference,
    v_r = ``reference_part(v, r)`` (the two-stage method, Forssell and Ljung 1999 sec. 6.2, Van
    den Hof and Schrama 1993): y = G F~(v_r) + e with e uncorrelated with v_r, so the refined
    linear block is consistent, and its map is F~(x) = E{F(v) | v_r = x}, F smoothed by the spread
    of the noise part of v (the input part the reference does not explain)."""
    return v if reference is None else reference_part(v, reference, runs=runs)


def solve_instrumental(phi: np.ndarray, target: np.ndarray, instruments: np.ndarray) -> np.ndarray:
    """theta of the square IV system Z^T Phi theta = Z^T target (Soderstrom and Stoica,
    "Instrumental variable methods for system identification", 1983, eq. 3.4), by least
    squares on the (small, square) normal matrix so that a nearly singular one gives its
    minimum-norm solution; IdentificationError when Z and Phi differ in shape."""
    if instruments.shape != phi.shape:
        raise IdentificationError(f"instruments {instruments.shape} for regressors {phi.shape}")
    return solve_least_squares(instruments.T @ phi, instruments.T @ target)
