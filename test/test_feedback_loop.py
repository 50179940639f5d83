"""The Hammerstein / non-linear feedback loop (paper 001, eq. 2): the compiled simulator against its
fallback, the map tails, and the diagnosis extension refined on the whole record against ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from hammer_ros.diagnosis.extensions import Context, FeedbackLayout, extend_output_feedback
from hammer_ros.diagnosis.hammerstein import HammersteinModel, fit_hammerstein, quantile_partition
from hammer_ros.diagnosis.split import split_record
from hammer_ros.identification import compiled_loops
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.piecewise_linear_ls import point_slope_map
from hammer_ros.identification.simulate import play_operator, simulate_hammerstein_feedback
from hammer_ros.identification.static_maps import PiecewiseLinearMap, with_tails

# the plant of the recovery tests: y = B/A [f(v) - h(y)], f(v) = v, h a one-sided kink
A_TRUE = np.real(np.poly([0.85, 0.6]))
B_TRUE = np.array([0.0, 0.3, 0.15])
KINK, KINK_SLOPE = 0.4, 1.2


def h_true(y: np.ndarray) -> np.ndarray:
    return KINK_SLOPE * np.maximum(np.asarray(y) - KINK, 0.0)


def plant_record(n: int = 3000, seed: int = 3, noise: float = 0.02):
    """Random steps held 8-30 samples, the loop simulated from rest, white output noise of
    ``noise`` times std(y)."""
    rng = np.random.default_rng(seed)
    levels, v = rng.uniform(-1.0, 2.0, n), []
    while len(v) < n:
        v.extend([levels[len(v)]] * int(rng.integers(8, 30)))
    v = np.asarray(v[:n])
    y = simulate_hammerstein_feedback(v, lambda x: x, h_true, LinearModel(B_TRUE, A_TRUE))
    return v, y + noise * np.std(y) * rng.standard_normal(n)


def test_compiled_and_fallback_loops_agree(monkeypatch):
    pytest.importorskip("numba")
    rng = np.random.default_rng(0)
    h = PiecewiseLinearMap([-0.5, 0.0, 0.7], [0.1, -0.05, 0.3], 0.4, -0.2, 0.05, 0.3)
    linear = LinearModel([0.0, 0.2, 0.1, -0.05], np.real(np.poly([0.9, 0.5 + 0.3j, 0.5 - 0.3j])))
    v = np.cumsum(rng.standard_normal(20000)) * 0.05
    compiled = simulate_hammerstein_feedback(v, np.tanh, h, linear)
    monkeypatch.setenv("HAMMER_ROS_NO_NUMBA", "1")
    assert not compiled_loops.numba_enabled()
    fallback = simulate_hammerstein_feedback(v, np.tanh, h, linear)
    generic = simulate_hammerstein_feedback(v, np.tanh, lambda x: h(x), linear)  # h called on arrays
    assert np.ptp(compiled) > 1.0  # the loop visits both tails and every interval
    assert np.any(compiled < -0.5) and np.any(compiled > 0.7)
    np.testing.assert_allclose(compiled, fallback, rtol=0, atol=1e-12)
    np.testing.assert_allclose(compiled, generic, rtol=0, atol=1e-9)
    monkeypatch.delenv("HAMMER_ROS_NO_NUMBA")
    x = rng.standard_normal(5000)
    np.testing.assert_allclose(compiled_loops.play(x, 0.3, 0.0, compiled=True),
                               compiled_loops.play(x, 0.3, 0.0, compiled=False), rtol=0, atol=1e-12)
    assert np.allclose(play_operator(np.repeat(x, 25), 0.6)[::25][:50], compiled_loops.play(x, 0.3, x[0])[:50])


def test_the_loop_matches_the_recursion_of_eq_2():
    """Two samples by hand: y(k) = [B f(v)](k) - b_1 h(y(k-1)) - a_1 y(k-1), B = [0, b_1]."""
    h = PiecewiseLinearMap([0.0, 1.0], [0.0, 0.5], 0.0, 2.0)
    linear = LinearModel([0.0, 0.5], [1.0, -0.8])
    y = simulate_hammerstein_feedback(np.array([2.0, 2.0, 2.0]), lambda x: x, h, linear)
    y1 = 0.5 * 2.0
    y2 = 0.5 * 2.0 - 0.5 * 0.5 * y1 + 0.8 * y1  # h(1) = 0.5 on the inner interval
    assert y[0] == 0.0 and y[1] == pytest.approx(y1, abs=1e-15) and y[2] == pytest.approx(y2, abs=1e-15)


def test_tails_continue_the_map_beyond_its_data():
    fmap = PiecewiseLinearMap([0.0, 1.0, 2.0], [0.0, 1.0, 1.5], 1.0, 0.25)
    x = np.array([-2.0, -1.0, 0.5, 3.0, 3.5, 4.0, 6.0])
    np.testing.assert_allclose(with_tails(fmap, -1.0, 3.0)(x), fmap(x))
    np.testing.assert_allclose(with_tails(fmap, -1.0, 3.0, "constant", "constant")(x),
                               [-1.0, -1.0, 0.5, 1.75, 1.75, 1.75, 1.75])
    # the slope falls by 0.25 over the 1.0 between the midpoints of the last two intervals:
    # 1.75 + 0.25 t - 0.125 t^2, held beyond its vertex t = 1
    np.testing.assert_allclose(with_tails(fmap, -1.0, 3.0, "slope", "polynomial")(x),
                               [-2.0, -1.0, 0.5, 1.75, 1.75 + 0.125 - 0.03125, 1.875, 1.875])
    with pytest.raises(ValueError):
        with_tails(fmap, 0.0, 1.0, "cubic")


def test_layout_pack_unpack_is_the_same_model():
    """pack moves h's linear part into A (paper 001 eq. 3) and rescales to the fixed coefficient:
    the simulated output does not change."""
    v, _ = plant_record(600)
    f_part, h_part = np.array([-0.3, 0.5, 1.2]), np.array([0.0, 0.5, 1.0, 1.8])
    layout = FeedbackLayout(2, np.array([0.0, 0.5, 0.1]), np.array([2]), f_part, 1, h_part, 2)
    f_map = point_slope_map(f_part, 1, np.array([1.0, 0.8, 1.1, 0.9]), 0.2)
    h_map = point_slope_map(h_part, 2, np.array([0.3, 0.1, 0.9, 1.5, 1.2]), 0.4)
    b = np.array([0.0, 0.3, 0.15])
    theta = layout.pack(A_TRUE, b, f_map, h_map)
    assert theta.size == layout.size
    a2, b2, f2, h2 = layout.unpack(theta)
    assert b2[1] == 0.5 and np.sum(h2.slopes) == pytest.approx(0.0, abs=1e-12) and h2(h_part[1:2])[0] == 0.0
    original = simulate_hammerstein_feedback(v, f_map, h_map, LinearModel(b, A_TRUE))
    np.testing.assert_allclose(simulate_hammerstein_feedback(v, f2, h2, LinearModel(b2, a2)), original, atol=1e-9)


def _aligned(model_a, model_b, h_map, y):
    """The estimate in the truth's normalisation (paper 001 eq. 3): scale s from b's largest
    coefficient, then alpha and an offset with h_hat / s = h_true - alpha y + c (least squares
    over the bulk of y); returns (poles of A_hat - alpha s B_hat, max map error over the bulk)."""
    s = B_TRUE[1] / model_b[1]
    grid = np.linspace(*np.quantile(y, [0.05, 0.95]), 200)
    target = h_map(grid) / s
    alpha, c = np.linalg.lstsq(np.column_stack([-grid, np.ones(grid.size)]), target - h_true(grid), rcond=None)[0]
    error = np.max(np.abs(target - (h_true(grid) - alpha * grid + c)))
    a_true_norm = model_a - alpha * s * np.pad(model_b, (0, model_a.size - model_b.size))
    return np.sort(np.roots(a_true_norm)), error / np.ptp(h_true(grid))


@pytest.mark.parametrize("baseline", ["fitted", "poor"])
def test_refined_extension_recovers_the_poles_and_the_feedback_map(baseline):
    """Noisy record of a known loop: the extension refined on the whole estimation record finds
    A's poles within 0.015 and h within 6 % of its range (after the normalisation of eq. 3), from a
    fitted Hammerstein baseline and from a poor one (wrong poles, h = 0): PLLS and the random
    starts do not depend on it. The baseline alone (h = 0) is far off on both counts."""
    v, y = plant_record()
    split = split_record(v, y, 0.7)
    base = fit_hammerstein(split.v_est, split.y_est, 2, 1, quantile_partition(split.v_est, 3), free_knots=False)
    if baseline == "poor":
        base = HammersteinModel(np.real(np.poly([0.3, 0.2])), np.array([0.0, 0.5, 0.0]), base.partition,
                                base.primary, np.full(base.slopes.size, 0.2), 0.0)
    ext = extend_output_feedback(Context(split, base, None, None))
    assert ext is not None and ext.details["starts"] >= 7
    assert set(ext.details["tails"]) == {"f", "h"}
    h_plot = ext.maps[1]
    h_hat = PiecewiseLinearMap(h_plot.x, h_plot.y, 0.0, 0.0)
    poles_true_norm, map_error = _aligned(np.asarray(ext.details["a"]), np.asarray(ext.details["b"]), h_hat,
                                          split.y_est)
    np.testing.assert_allclose(poles_true_norm, np.sort(np.roots(A_TRUE)), atol=0.015)
    assert map_error < 0.06
    rms = np.sqrt(np.mean((ext.validation_output - split.y_val) ** 2))
    assert rms < 0.04 * np.std(split.y_val)  # the noise is 0.02 std(y)



def test_a_record_that_starts_at_rest_away_from_its_first_input_is_fitted_from_its_first_sample():
    """The plant held at rest at u_a = -0.8, then the record starts with the steps (its first input
    is not u_a): the extension estimates the record's initial state with the loop, so its
    ``initial_input`` is u_a (the truth, within 3 % of the input range; a start at rest at the
    first input would be 2.2 off), and A's poles come out right."""
    u_a, hold = -0.8, 400
    v, _ = plant_record(2400, seed=5, noise=0.0)
    v = np.concatenate([np.full(hold, u_a), v])
    y = simulate_hammerstein_feedback(v, lambda x: x, h_true, LinearModel(B_TRUE, A_TRUE))[hold:]
    v = v[hold:]
    assert abs(v[0] - u_a) > 1.0
    y = y + 0.02 * np.std(y) * np.random.default_rng(6).standard_normal(y.size)
    split = split_record(v, y, 0.7)
    base = fit_hammerstein(split.v_est, split.y_est, 2, 1, quantile_partition(split.v_est, 3), free_knots=False)
    ext = extend_output_feedback(Context(split, base, None, None))
    assert abs(ext.details["initial_input"] - u_a) < 0.03 * np.ptp(v), ext.details["initial_input"]
    a, b = np.asarray(ext.details["a"]), np.asarray(ext.details["b"])
    h_plot = ext.maps[1]
    poles, _ = _aligned(a, b, PiecewiseLinearMap(h_plot.x, h_plot.y, 0.0, 0.0), split.y_est)
    np.testing.assert_allclose(poles, np.sort(np.roots(A_TRUE)), atol=0.015)
