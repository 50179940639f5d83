"""The compiled free run of a polynomial Hammerstein model (``free_run_kernel``) against the reference
(``Runs.initial_states`` and ``Runs.simulate`` of one run: a polynomial map, then ``lfilter``), and its
fit on a window (``window_fit``: the roots bit for bit ``LinearModel``'s, fit and rms to rounding)."""

from functools import partial

import numpy as np
import pytest

from hammer_ros.identification.free_run_kernel import (
    hammerstein_fit,
    hammerstein_free_run,
    polynomial_hammerstein,
    remember_roots,
)
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.result import IdentificationResult, fit_and_rms
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
    ([0.0, 0.2, 0.1, 0.05, 0.02], [1.0, -1.0, 0.14, 0.084, -0.018], [0.0, 1.0, -0.2]),  # order 4: the last scalar form
    ([0.1, 0.2, 0.1, 0.05, 0.02, 0.01], [1.0, -0.9, 0.17, 0.051, -0.0092, -0.0012], [0.3, 1.0]),  # order 5: the array
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
        got = hammerstein_free_run(polynomial_hammerstein(simulate), v, y, settle)
    assert got is not None
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12, equal_nan=True)


def test_other_models_and_no_numba_take_the_reference(monkeypatch):
    linear = LinearModel(np.array([0.0, 0.5]), np.array([1.0, -0.5]))
    v = np.linspace(0.0, 1.0, 50)
    knee = PiecewiseLinearMap(np.array([0.5]), np.array([0.5]), 1.0, 2.0)
    piecewise = partial(simulate_hammerstein, nonlinearity=knee, linear=linear)
    assert polynomial_hammerstein(piecewise) is None
    assert polynomial_hammerstein(linear.simulate) is None
    polynomial = partial(simulate_hammerstein, nonlinearity=PolynomialMap(np.array([0.0, 1.0])), linear=linear)
    parts = polynomial_hammerstein(polynomial)
    assert hammerstein_free_run(parts, v, v, 10) is not None
    assert hammerstein_fit(parts, v, v[::-1], 10) is not None
    assert hammerstein_fit(parts, v, v[:-1], 10) is None  # uneven: the reference decides
    unstable = LinearModel(np.array([0.0, 1.0]), np.array([1.0, np.nan]))
    remember_roots(unstable)  # not finite: left to LinearModel, which raises
    assert "_zpk" not in unstable.__dict__
    monkeypatch.setenv("HAMMER_ROS_NO_NUMBA", "1")
    assert hammerstein_free_run(parts, v, v, 10) is None
    assert hammerstein_fit(parts, v, v, 10) is None
    fresh = LinearModel(linear.b, linear.a)
    remember_roots(fresh)
    assert "_zpk" not in fresh.__dict__
    result = IdentificationResult("x", linear, polynomial)
    assert result.window_fit(v, v[::-1]) == fit_and_rms(v[::-1], result.free_run(v, v[::-1]))


@pytest.mark.parametrize("seed", range(6))
def test_window_fit_has_the_reference_roots_and_figures(seed):
    """``window_fit`` (one compiled call) on models with delays, trailing zeros of b or a (roots at 0,
    the common ones cancelled), complex and real poles: the poles and zeros it leaves in the model
    equal ``LinearModel``'s bit for bit, its rest length ``rest_length``'s, its fit and rms the
    reference's to rounding (``fit_and_rms`` of ``free_run``)."""
    rng = np.random.default_rng(seed)
    for trial in range(60):
        n = int(rng.integers(1, 6))
        delay = int(rng.integers(0, n + 1)) if trial % 3 else 0
        a = np.concatenate([[1.0], rng.uniform(-0.6, 0.6, n) / n])
        a[-1] = 0.0 if trial % 7 == 0 else a[-1]
        b = np.concatenate([np.zeros(delay), rng.standard_normal(n + 1 - delay)])
        b = b[: max(1, b.size - int(rng.integers(0, 3)))] if trial % 5 == 0 else b
        b[-1] = 0.0 if trial % 11 == 0 and b.size > 1 else b[-1]
        linear = LinearModel(b, a)
        fmap = PolynomialMap(np.concatenate([rng.standard_normal(1), [1.0], rng.standard_normal(2) * 0.3]))
        simulate = partial(simulate_hammerstein, nonlinearity=fmap, linear=linear)
        v = rng.standard_normal(400)
        y = simulate(v) + 0.1 * rng.standard_normal(v.size)
        result = IdentificationResult("cls-markov", linear, simulate)
        fit, rms = result.window_fit(v, y)
        reference = LinearModel(b, a)
        np.testing.assert_array_equal(result.zeros, reference.zeros, strict=True)
        np.testing.assert_array_equal(result.poles, reference.poles, strict=True)
        expected_fit, expected_rms = fit_and_rms(y, IdentificationResult("x", reference, simulate).free_run(v, y))
        assert fit == pytest.approx(expected_fit, rel=1e-12, abs=1e-12)
        assert rms == pytest.approx(expected_rms, rel=1e-12)
