"""The fleet's change test (``hammer_ros.fleet.changes``, pure numpy): steps and drifts found from
the right bag, stationary noise and single outliers left alone, the robust helpers exact."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hammer_ros.fleet import changes
from hammer_ros.fleet.changes import cusum_change, group_changes, relative_noise, robust_scale, theil_sen


def noisy(n: int, seed: int, level: float = 1.0, rel: float = 0.03) -> np.ndarray:
    return level * (1 + rel * np.random.default_rng(seed).standard_normal(n))


@pytest.mark.parametrize("start, size", [(6, -0.25), (10, 0.3), (4, -0.15)])
def test_a_step_is_flagged_from_its_first_bag_with_its_size(start, size):
    x = noisy(20, seed=start, rel=0.02)
    x[start:] *= 1 + size
    test = cusum_change(x, "gain", noise=0.02)
    c = test.change
    assert c is not None and c.onset == start and c.direction == int(np.sign(size))
    assert c.flagged == tuple(range(start, 20))
    assert c.size == pytest.approx(size, abs=0.05)
    assert c.alarm >= c.onset


def test_a_drift_is_flagged_from_where_it_starts():
    days = np.arange(25.0)
    x = noisy(25, seed=3, level=2.0, rel=0.015)
    x *= 1 - 0.04 * np.clip(days - 11, 0, None)  # -4 %/day from day 12 (index 12)
    test = cusum_change(x, "gain", times=days * changes.DAY, noise=0.015)
    assert test.change is not None and test.change.onset == 12 and test.change.direction == -1
    assert test.change.size < -0.3
    assert test.trend_per_day < 0


def test_stationary_noise_raises_almost_no_alarm():
    alarms = sum(cusum_change(noisy(30, seed, rel=0.03), noise=0.03).change is not None for seed in range(300))
    # two sides, 27 tested bags each (an exact-normal CUSUM with K 0.5, H 5 alarms in about 6 %)
    assert alarms / 300 < 0.05, alarms


def test_a_tight_history_does_not_turn_noise_into_alarms():
    # the first three bags agree to 0.1 % by chance; the real scatter is 3 %
    x = np.r_[1.0, 1.001, 0.999, noisy(20, seed=7, rel=0.03)]
    assert cusum_change(x, noise=0.0).z[3:] != cusum_change(x, noise=0.03).z[3:]
    assert cusum_change(x, noise=0.03).change is None


def test_one_outlier_is_not_a_change_but_a_gross_one_is():
    x = noisy(20, seed=11, rel=0.01)
    scale = robust_scale(x[:3], 0.02)[1]
    mild = x.copy()
    mild[9] += 4 * scale  # 4 scale units: S reaches 3.5 < H and decays
    assert cusum_change(mild, noise=0.02).change is None
    gross = x.copy()
    gross[9] += 12 * scale
    c = cusum_change(gross, noise=0.02).change
    assert c is not None and c.onset == 9


def test_nan_values_are_skipped():
    x = noisy(16, seed=5, rel=0.01)
    x[8:] *= 0.7
    x[[2, 9]] = np.nan
    c = cusum_change(x, noise=0.02).change
    assert c is not None and c.onset == 8 and 9 not in c.flagged and c.flagged[-1] == 15
    assert math.isnan(cusum_change(x).z[9])


def test_too_short_a_series_is_never_flagged():
    assert cusum_change([1.0, 0.5, 0.2]).change is None


def test_robust_scale_and_relative_noise():
    m, s = robust_scale(np.array([10.0, 10.0, 10.0, 10.0, 10.0]))
    assert m == 10.0 and s == pytest.approx(changes.REL_FLOOR * 10.0)
    m, s = robust_scale(np.array([1.0, 2.0, 3.0, 4.0, 100.0]))  # the outlier does not move them
    assert m == 3.0 and s == pytest.approx(changes.MAD_SMALL_SAMPLE[5] * changes.MAD_TO_SIGMA * 1.0)
    rng = np.random.default_rng(2)
    series = [5.0 * (1 + 0.04 * rng.standard_normal(40)) for _ in range(5)]
    assert relative_noise(series) == pytest.approx(0.04, rel=0.2)
    stepped = [s.copy() for s in series]
    stepped[0][20:] *= 0.6  # a step and a drift barely move the pooled scatter
    stepped[1] *= 1 - 0.01 * np.arange(40)
    assert relative_noise(stepped) == pytest.approx(relative_noise(series), rel=0.15)
    assert math.isnan(relative_noise([[1.0, 1.1]]))


def test_theil_sen_is_the_slope_of_a_line_despite_an_outlier():
    t = np.arange(12.0)
    x = 3.0 - 0.5 * t
    x[4] = 40.0
    assert theil_sen(t, x) == pytest.approx(-0.5)


def test_group_changes_names_the_quantity_and_the_first_bag():
    days = np.arange(12.0) * changes.DAY
    gain = noisy(12, seed=1, rel=0.01)
    gain[7:] *= 0.8
    tests, found = group_changes("robot_07/joint3", days, {"gain": gain, "tau": noisy(12, seed=2, rel=0.01)},
                                 {"gain": 0.01, "tau": 0.01})
    assert set(tests) == {"gain", "tau"}
    assert [(c.group, c.quantity, c.first_index, c.bags) for c in found] == [("robot_07/joint3", "gain", 7, 5)]
    assert found[0].size == pytest.approx(-0.2, abs=0.03) and found[0].latest == gain[-1]
