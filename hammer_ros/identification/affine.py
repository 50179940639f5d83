"""Inputs as robots move them: steps, ramps, held setpoints.

- ``degraded_to_gain``: an input with two distinct levels determines F at two points only, so
  a Hammerstein model's map is replaced by the affine map through them, F(v) = F(v1) + (F(v2) -
  F(v1)) (v - v1) / (v2 - v1): the same free-run output on the record, and no curvature
  that the data cannot show (``trust.excitation_warnings`` says so with ``not_exciting``).
- ``affine_start``: a start for ``refinement.refine_result`` that does not depend on the
  method's assumptions about the input: the equation-error ARX fit with an intercept,

      y(k) = -a_1 y(k-1) - ... - a_n y(k-n) + b_d v(k-d) + ... + b_n v(k-n) + c,

  over the rows whose lags stay in their run (``Runs.rows``), and the method's map family set
  to the affine map F(v) = v + c / B(1). On a step the correlation methods' estimate can be far
  off (their input assumption fails) and an output-error descent from it stops in a poor
  local minimum; the ARX fit is biased by noise but lies in the output-error optimum's basin.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np

from .linear import LinearModel
from .regression import lagged_columns, solve_least_squares
from .result import IdentificationResult
from .runs import Runs
from .simulate import simulate_hammerstein
from .static_maps import PiecewiseLinearMap, PolynomialMap


def degraded_to_gain(result: IdentificationResult, v: np.ndarray) -> IdentificationResult:
    """``result`` with its input map replaced by the affine map through its values at the input's two
    levels (module docstring); unchanged unless v has exactly two levels and the model is a plain
    Hammerstein chain with a map (no feedback map, no parallel path)."""
    levels = np.unique(np.asarray(v, dtype=float))
    f = result.nonlinearity
    if (levels.size != 2 or f is None or result.feedback_nonlinearity is not None
            or result.extra.get("parallel_path") or (isinstance(f, PolynomialMap) and f.coefficients.size <= 2)):
        return result
    values = np.asarray(f(levels), dtype=float)
    slope = float(values[1] - values[0]) / float(levels[1] - levels[0])
    affine = PolynomialMap(np.array([float(values[0]) - slope * float(levels[0]), slope]))
    bounds = result.uncertainty if result.uncertainty is None else replace(result.uncertainty, map_covariance=None)
    return replace(result, nonlinearity=affine, uncertainty=bounds,
                   simulate=partial(simulate_hammerstein, nonlinearity=affine, linear=result.linear))


def affine_start(result: IdentificationResult, v: np.ndarray, y: np.ndarray,
                 runs: Runs) -> IdentificationResult | None:
    """The start of the module docstring in ``result``'s structure, None when the structure has a
    feedback map or a parallel path, or a map that has no affine member here (a map known only
    at points), or when the fit fails."""
    f = result.nonlinearity
    if result.feedback_nonlinearity is not None or result.extra.get("parallel_path"):
        return None
    if f is not None and not isinstance(f, (PolynomialMap, PiecewiseLinearMap)):
        return None
    n = result.linear.a.size - 1
    b = result.linear.b
    delay = int(np.argmax(np.abs(b) > 0)) if np.any(b) else 1
    rows = runs.rows(n)
    if n < 1 or rows.size <= 2 * n + 2:
        return None
    phi = np.column_stack([-lagged_columns(y, range(1, n + 1), rows), lagged_columns(v, range(delay, n + 1), rows),
                           np.ones(rows.size)])
    theta = solve_least_squares(phi, y[rows])
    if not np.all(np.isfinite(theta)):
        return None
    a = np.concatenate([[1.0], theta[:n]])
    b_new = np.zeros(max(b.size, n + 1))
    b_new[delay : n + 1] = theta[n:-1]
    gain_b = float(b_new.sum())
    offset = float(theta[-1]) / gain_b if abs(gain_b) > 1e-12 else 0.0
    linear = LinearModel(b_new, a)
    if f is None:
        return replace(result, linear=linear, simulate=linear.simulate, uncertainty=None)
    if isinstance(f, PolynomialMap):
        affine = PolynomialMap(np.concatenate([[offset, 1.0], np.zeros(max(f.coefficients.size - 2, 0))]))
    else:
        affine = PiecewiseLinearMap(f.breakpoints, f.breakpoints + offset, 1.0, 1.0)
    return replace(result, linear=linear, nonlinearity=affine, uncertainty=None,
                   simulate=partial(simulate_hammerstein, nonlinearity=affine, linear=linear))
