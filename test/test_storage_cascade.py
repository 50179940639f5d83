"""Two first-order storages in series (``storage_cascade``), the second form of ``output_feedback``:
the compiled recursion against its fallback and against linear-systems theory, the linear start
against the baseline, and the fit on a two-tank plant against its true outflow map."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from hammer_ros.diagnosis.diagnose import diagnose
from hammer_ros.diagnosis.extensions import Context, extend_output_feedback
from hammer_ros.diagnosis.hammerstein import fit_hammerstein, quantile_partition
from hammer_ros.diagnosis.split import split_record
from hammer_ros.diagnosis.storage_cascade import CascadeLayout, linear_cascade_start, plausible_rest, storage_poles
from hammer_ros.identification.compiled_loops import storage_cascade
from hammer_ros.identification.static_maps import PiecewiseLinearMap
from hammer_ros.reproduce.real import RECORDS

# the two-tank plant: x1(k+1) = x1 + B u - C1 sqrt(x1), x2(k+1) = x2 + C1 sqrt(x1(k+1)) - C2 sqrt(x2)
B_IN, C1, C2 = 0.05, 0.1, 0.08


def knot_form(knots, values, slopes, curvature_left=0.0, curvature_right=0.0):
    slopes = np.asarray(slopes, float)
    return PiecewiseLinearMap(knots, values, slopes[0], slopes[-1], curvature_left, curvature_right)


def two_tanks(u: np.ndarray) -> np.ndarray:
    """The plant from rest at u(0) (its levels at equilibrium), y = x2."""
    x1 = (B_IN * u[0] / C1) ** 2
    x2 = (C1 * np.sqrt(x1) / C2) ** 2
    y = np.empty(u.size)
    for k in range(u.size):
        y[k] = x2
        x1 = max(x1 + B_IN * u[k] - C1 * np.sqrt(x1), 0.0)
        x2 = max(x2 + C1 * np.sqrt(x1) - C2 * np.sqrt(x2), 0.0)
    return y


def tank_record(n: int = 3000, seed: int = 4, noise: float = 0.01):
    rng = np.random.default_rng(seed)
    u: list[float] = []
    while len(u) < n:
        u.extend([rng.uniform(0.5, 3.0)] * int(rng.integers(20, 80)))
    u = np.asarray(u[:n])
    y = two_tanks(u)
    return u, y + noise * np.std(y) * rng.standard_normal(n)


def test_compiled_and_fallback_cascades_agree():
    pytest.importorskip("numba")
    rng = np.random.default_rng(1)
    drive = 0.1 + 0.05 * rng.standard_normal(20000)
    first = knot_form([0.5, 1.0, 2.0], [0.05, 0.09, 0.15], [0.1, 0.08, 0.06, 0.04], 0.0, -0.01)
    between = knot_form([0.5, 1.5], [0.04, 0.1], [0.08, 0.06, 0.0])  # a cap: an overflow
    second = knot_form([0.6, 1.2], [0.06, 0.1], [0.12, 0.07, 0.05])
    compiled = storage_cascade(drive, first, between, second, compiled=True)
    fallback = storage_cascade(drive, first, between, second, compiled=False)
    assert np.ptp(compiled) > 0.5
    np.testing.assert_allclose(compiled, fallback, rtol=0, atol=1e-12)


def test_linear_maps_give_the_linear_cascade_transfer_function():
    """h_i(x) = (1 - p_i) x, g(x) = c x: y = c q^-1 / ((1 - p1 q^-1)(1 - p2 q^-1)) [drive]."""
    p1, p2, c = 0.9, 0.7, 0.4
    drive = np.random.default_rng(2).standard_normal(500)

    def linear(slope):
        return knot_form([0.0], [0.0], [slope, slope])

    y = storage_cascade(drive, linear(1 - p1), linear(c), linear(1 - p2))
    expected = signal.lfilter([0.0, c], np.convolve([1.0, -p1], [1.0, -p2]), drive)
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-12)


def test_the_linear_start_has_the_baselines_poles_and_steady_state():
    u, y = tank_record(noise=0.0)
    base = fit_hammerstein(u, y, 2, 1, quantile_partition(u, 3), free_knots=False)
    poles = storage_poles(base.linear.poles)
    assert poles is not None and poles[0] >= poles[1]
    layout, theta = linear_cascade_start(base, base.partition, poles, u, 1)
    assert isinstance(layout, CascadeLayout)
    for level in (0.8, 2.5):
        rest = layout.simulate(theta, np.full(50, level), level, 3000)
        expected = np.sum(base.b) / np.sum(base.a) * base.static(np.array([level]))[0]
        np.testing.assert_allclose(rest, expected, rtol=1e-6)
    step = layout.simulate(theta, np.r_[np.full(10, 1.0), np.full(400, 2.0)], 1.0, 3000)
    modes = np.diff(step[12:])  # two real modes: the increments decay at the slower pole
    np.testing.assert_allclose(modes[-1] / modes[-2], poles[0], atol=2e-3)


def test_two_tanks_are_fitted_as_storages_in_series_with_their_outflow():
    """A noisy two-tank record (Bernoulli outflows): the extension chooses the cascade over the
    single loop, predicts the validation data to about its noise (1 % of std(y)), and its h2 is
    the second tank's true outflow C2 sqrt(y) within 5 % of its range (up to the offset that
    the representation moves into g)."""
    u, y = tank_record()
    split = split_record(u, y, 0.7)
    base = fit_hammerstein(split.v_est, split.y_est, 2, 1, quantile_partition(split.v_est, 3), free_knots=False)
    ext = extend_output_feedback(Context(split, base, None, None))
    assert ext.details["form"] == "storage_cascade" and set(ext.details["tails"]) == {"f", "h"}
    rms = np.sqrt(np.mean((ext.validation_output - split.y_val) ** 2))
    base_rms = np.sqrt(np.mean((split.validation_output(base.simulate) - split.y_val) ** 2))
    assert rms < 0.03 * np.std(split.y_val) and base_rms > 3 * rms, (rms, base_rms)
    h2 = ext.maps[3]
    bulk = (h2.x >= np.quantile(split.y_est, 0.05)) & (h2.x <= np.quantile(split.y_est, 0.95))
    difference = h2.y[bulk] - C2 * np.sqrt(h2.x[bulk])
    assert np.ptp(difference) < 0.05 * np.ptp(C2 * np.sqrt(h2.x[bulk]))


def test_a_storage_that_drains_without_bound_has_no_plausible_rest():
    """The linear start's rest states follow the baseline's steady output; the same cascade with
    an h1 that falls below the first knot (the first storage drains faster the emptier it is)
    has no equilibrium at the lowest inputs and is not kept."""
    u, y = tank_record(noise=0.0)
    base = fit_hammerstein(u, y, 2, 1, quantile_partition(u, 3), free_knots=False)
    layout, theta = linear_cascade_start(base, base.partition, storage_poles(base.linear.poles), u, 1)
    assert plausible_rest(layout, theta, u, y, 3000)
    broken = theta.copy()
    nf = layout.sizes()[0]
    broken[nf] = -0.05  # the slope of h1 below its first knot
    assert not plausible_rest(layout, broken, u, y, 3000)


def test_the_cascaded_tanks_with_the_order_chosen_are_two_storages_too():
    """The benchmark record (1024 estimation samples -> the test record) without a nominal order:
    the order chosen is 3, the storages start from its two slowest poles, and the diagnosis
    names the outflow feedback at the level of the best black-box models (<= 0.45 V)."""
    split = RECORDS["cascaded_tanks"].load()
    d = diagnose(split, None).diagnosis
    assert d.baseline_model["order"] >= 3
    assert d.cause == "output_feedback" and d.details["form"] == "storage_cascade"
    assert d.extended.rms <= 0.45 and d.gain >= 1.15
