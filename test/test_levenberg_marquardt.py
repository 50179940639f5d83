"""``levenberg_marquardt``: MINPACK's lmder as scipy 1.17's ``least_squares(method="lm")`` runs it,
checked against known minima (ground truth) and against scipy itself (the same trial points and the
same minimum to the bit, where scipy's norm recomputation past the column does not occur), and its
evaluation budget."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from hammer_ros.identification.levenberg_marquardt import levenberg_marquardt

T = np.linspace(0.0, 10.0, 2000)
TRUE = np.array([2.0, 0.3, 1.1, 0.2, 0.5, 0.05])


def _model(p: np.ndarray) -> np.ndarray:
    return p[0] * np.exp(-p[1] * T) * np.cos(p[2] * T + p[3]) + p[4] * np.exp(-p[5] * T)


def _rosenbrock(p: np.ndarray) -> np.ndarray:
    return np.array([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])


@pytest.mark.parametrize("x0", [[1.0, 0.2, 1.0, 0.0, 0.3, 0.1], [3.0, 0.5, 0.7, 1.0, 0.0, 0.0]])
def test_a_noiseless_fit_recovers_the_true_parameters_as_scipy_does(x0):
    y = _model(TRUE)
    solution = levenberg_marquardt(lambda p: _model(p) - y, np.array(x0), 200)
    assert solution.status in (1, 2, 3, 4) and solution.cost < 1e-20
    np.testing.assert_allclose(solution.x, TRUE, rtol=1e-8)
    reference = least_squares(lambda p: _model(p) - y, x0, method="lm", x_scale="jac", max_nfev=200)
    np.testing.assert_allclose(solution.x, reference.x, rtol=1e-8)


@pytest.mark.parametrize("x0", [[1.0, 0.2, 1.0, 0.0, 0.3, 0.1], [3.0, 0.5, 0.7, 1.0, 0.0, 0.0]])
def test_a_noisy_fit_takes_scipys_trial_points_to_its_minimum_to_the_bit(x0):
    y = _model(TRUE) + 0.01 * np.random.default_rng(1).standard_normal(T.size)
    for budget in (60, 4):  # converged, and stopped by the budget midway
        solution = levenberg_marquardt(lambda p: _model(p) - y, np.array(x0), budget, ftol=1e-6, xtol=1e-6)
        reference = least_squares(lambda p: _model(p) - y, x0, method="lm", x_scale="jac", max_nfev=budget,
                                  ftol=1e-6, xtol=1e-6)
        assert solution.evaluations == reference.nfev
        np.testing.assert_array_equal(solution.x, reference.x)
        assert solution.cost == reference.cost


@pytest.mark.parametrize("x0", [[-1.2, 1.0], [0.0, 0.0]])
def test_rosenbrock_reaches_its_minimum_at_one_one(x0):
    solution = levenberg_marquardt(_rosenbrock, np.array(x0), 100)
    np.testing.assert_allclose(solution.x, [1.0, 1.0], atol=1e-7)
    assert solution.evaluations == least_squares(_rosenbrock, x0, method="lm", x_scale="jac", max_nfev=100).nfev


def test_the_evaluation_budget_counts_the_start_and_the_trial_points():
    y = _model(TRUE)
    solution = levenberg_marquardt(lambda p: _model(p) - y, np.array([3.0, 0.5, 0.7, 1.0, 0.0, 0.0]), 4)
    assert solution.status == 5 and solution.evaluations == 4
    assert solution.jacobians >= 1 and solution.cost > 1e-6  # stopped far from the minimum


def test_fewer_residuals_than_variables_is_an_error():
    with pytest.raises(ValueError, match="1 residuals for 2 variables"):
        levenberg_marquardt(lambda p: np.array([p[0] + p[1]]), np.zeros(2), 10)
