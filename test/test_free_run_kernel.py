"""The compiled free run of a polynomial Hammerstein model (``free_run_kernel``) against the reference
(``Runs.initial_states`` and ``Runs.simulate`` of one run: a polynomial map, then ``lfilter``)."""

from functools import partial

import numpy as np
import pytest

from hammer_ros.identification.free_run_kernel import hammerstein_free_run
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.runs import Runs, rest_length
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.identification.static_maps import PiecewiseLinearMap, PolynomialMap


def reference_free_run(simulate, v, y, settle):
    runs = Runs.one(v.size)
    return runs.simulate(simulate, v, settle, runs.initial_states(simulate, v, y, settle))


MODELS = [  # (b, a, polynomial coefficients)
    ([0.0, 0.5, 0.2], [1.0, -1.2, 0.5], [0.1, 1.0, 0.0, -0.3]),  # CLS's order 2 with a cubic map
    ([0.0, 0.3, 0.1, 0.05], [1.0, -1.5, 0.7, -0.1], [0.0, 1.0, 0.2, 0.4]),
    ([0.2, 0.1], [1.0, -0.9], [0.0, 1.0]),  # order 1, a direct feed-through, a linear map
    ([0.0, 1.0], [1.0, -1.0], [0.5, 1.0, 0.1]),  # an integrator (no rest: the steady state is unbounded)
    ([0.0, 0.4], [2.0, -1.0], [1.0, 2.0]),  # a_0 != 1 (lfilter divides by it)
    ([0.7], [1.0], [0.0, 1.0, 0.0, 0.0]),  # a static gain, a map with trailing zeros
    ([0.0, 0.5], [1.0, -1.3], [0.0, 1.0]),  # unstable: inf and nan as the reference's
]


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("start", ["rest", "zero"])
def test_free_run_equals_the_reference(model, start):
    b, a, coefficients = model
    linear = LinearModel(np.asarray(b), np.asarray(a))
    simulate = partial(simulate_hammerstein, nonlinearity=PolynomialMap(np.asarray(coefficients)), linear=linear)
    rng = np.random.default_rng(len(b) + len(coefficients))
    v = 1.5 + 0.3 * rng.standard_normal(700)
    settle = rest_length(linear.poles)
    # a record that starts at rest at v(0) or from zero state: the two starts the choice is between
    y = reference_free_run(simulate, v, np.zeros(v.size) if start == "zero" else simulate(np.full(v.size, v[0])),
                           settle) + 0.01 * rng.standard_normal(v.size)
    expected = reference_free_run(simulate, v, y, settle)
    with np.errstate(all="ignore"):
        got = hammerstein_free_run(simulate, v, y, settle)
    assert got is not None
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12, equal_nan=True)


def test_other_models_and_no_numba_take_the_reference(monkeypatch):
    linear = LinearModel(np.array([0.0, 0.5]), np.array([1.0, -0.5]))
    v = np.linspace(0.0, 1.0, 50)
    knee = PiecewiseLinearMap(np.array([0.5]), np.array([0.5]), 1.0, 2.0)
    piecewise = partial(simulate_hammerstein, nonlinearity=knee, linear=linear)
    assert hammerstein_free_run(piecewise, v, v, 10) is None
    assert hammerstein_free_run(linear.simulate, v, v, 10) is None
    polynomial = partial(simulate_hammerstein, nonlinearity=PolynomialMap(np.array([0.0, 1.0])), linear=linear)
    assert hammerstein_free_run(polynomial, v, v, 10) is not None
    monkeypatch.setenv("HAMMER_ROS_NO_NUMBA", "1")
    assert hammerstein_free_run(polynomial, v, v, 10) is None
