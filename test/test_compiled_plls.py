"""The compiled PLLS-Hammerstein solve (``plls_kernel.plls_solve``) against the numpy reference on random
systems: estimates and confidence bounds equal to 1e-9 relative, orders 1-3, relative degrees 0-order,
the default and given partitions; the other cases stay on the reference."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from relative_tolerance import assert_close

from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.methods import IdentifyOptions, identify
from hammer_ros.identification.piecewise_linear_ls import compiled_plls, default_partition, plls
from hammer_ros.identification.runs import Runs
from hammer_ros.identification.simulate import add_noise, simulate_hammerstein
from hammer_ros.identification.static_maps import PiecewiseLinearMap

pytest.importorskip("numba")



def random_case(seed: int):
    """A random stable plant (order 1-3, relative degree 0-order, real poles and zeros inside radius
    0.85), a random monotone piecewise-linear map with a dead zone or a saturation, a uniform input with a
    random offset and 1-5 % output noise: (u, y, order, delay)."""
    rng = np.random.default_rng(seed)
    order = int(rng.integers(1, 4))
    delay = int(rng.integers(0, order + 1))
    linear = LinearModel.from_zeros_poles(rng.uniform(-0.85, 0.85, order - delay), rng.uniform(-0.85, 0.85, order))
    knots = np.sort(rng.uniform(-0.8, 0.8, 3))
    fmap = PiecewiseLinearMap(knots, np.cumsum(rng.uniform(0.0, 1.0, 3)), rng.uniform(0.2, 2.0), rng.uniform(0.0, 2.0))
    u = rng.uniform(-1.0, 1.0, int(rng.integers(1000, 4001))) + rng.normal(0.0, 0.1)
    y = simulate_hammerstein(u, fmap, linear)
    return u, add_noise(y, rng.uniform(0.01, 0.05), seed=rng), order, delay


FIGURES = {
    "b": lambda e: e.linear.b, "a": lambda e: e.linear.a, "poles": lambda e: e.linear.poles,
    "zeros": lambda e: e.linear.zeros, "knots": lambda e: e.nonlinearity.breakpoints,
    "values": lambda e: e.nonlinearity.values,
    "slopes": lambda e: [e.nonlinearity.slope_left, e.nonlinearity.slope_right],
    "poles_std": lambda e: e.uncertainty.poles_std, "zeros_std": lambda e: e.uncertainty.zeros_std,
    "map_covariance": lambda e: e.uncertainty.map_covariance,
}


def assert_equal_estimates(compiled, reference, label: str) -> None:
    assert reference.uncertainty is not None and compiled.uncertainty.how == reference.uncertainty.how
    for name, figure in FIGURES.items():
        assert_close(figure(compiled), figure(reference), f"{label}: {name}")


@pytest.mark.parametrize("seed", range(16))
def test_the_compiled_solve_equals_the_reference(seed):
    u, y, order, delay = random_case(seed)
    partition = default_partition(u)
    assert compiled_plls(u, y, partition, max(1, partition.size // 2), order, delay, True) is not None
    compiled = plls(u, y, order, delay, instrumental=True, uncertainty=True)
    reference = plls(u, y, order, delay, instrumental=True, uncertainty=True, compiled=False)
    assert compiled.primary_index == reference.primary_index and compiled.feedback is None
    assert_equal_estimates(compiled, reference, f"seed {seed}, order {order}, delay {delay}")


def test_identify_and_a_given_partition_equal_the_reference():
    """``identify plls-hammerstein`` (what the engine runs) with a given partition and primary index."""
    u, y, order, delay = random_case(100)
    options = IdentifyOptions(order=order, delay=delay, partition=(-0.5, 0.0, 0.4))
    compiled = identify("plls-hammerstein", u, y, options)
    reference = plls(u, y, order, delay, partition=np.array(options.partition), instrumental=True, uncertainty=True,
                     compiled=False)
    assert compiled.extra["plls"]["primary_index"] == reference.primary_index
    assert_equal_estimates(compiled, reference, "identify")
    for primary in (1, 3):
        assert_equal_estimates(
            plls(u, y, order, delay, partition=np.array(options.partition), primary_index=primary,
                 instrumental=True, uncertainty=True),
            plls(u, y, order, delay, partition=np.array(options.partition), primary_index=primary,
                 instrumental=True, uncertainty=True, compiled=False), f"primary {primary}")


def test_an_unstable_first_estimate_keeps_least_squares_in_both():
    """An unstable plant (pole 1.01): the least-squares estimate is unstable, no IV pass, the bounds of
    least squares, in both."""
    rng = np.random.default_rng(5)
    u = rng.uniform(-1.0, 1.0, 1000)
    y = simulate_hammerstein(u, np.tanh, LinearModel([0.0, 1.0], [1.0, -1.01]))
    y = y + 0.01 * np.std(y) * rng.standard_normal(u.size)
    compiled = plls(u, y, 1, 1, instrumental=True, uncertainty=True)
    reference = plls(u, y, 1, 1, instrumental=True, uncertainty=True, compiled=False)
    assert not reference.linear.is_stable()
    assert "least squares" in reference.uncertainty.how
    assert_equal_estimates(compiled, reference, "unstable")


def test_where_the_reference_decides_the_compiled_solve_steps_aside():
    """A NaN in the record, too few samples for the regression: the kernel hands over (None) and ``plls``
    answers or raises as the reference does; other settings (beta, several runs) take the reference."""
    u, y, order, delay = random_case(3)
    partition = default_partition(u)
    with_nan = y.copy()
    with_nan[50] = np.nan
    assert compiled_plls(u, with_nan, partition, 1, order, delay, True) is None
    assert compiled_plls(u[:30], y[:30], partition, 1, order, delay, True) is None
    runs = Runs.from_lengths([u.size // 2, u.size - u.size // 2])
    for kwargs in ({"beta": 1.0}, {"runs": runs}):
        np.testing.assert_array_equal(
            plls(u, y, order, delay, instrumental=True, uncertainty=True, **kwargs).linear.b,
            plls(u, y, order, delay, instrumental=True, uncertainty=True, compiled=False, **kwargs).linear.b)


def test_no_numba_in_the_environment_gives_the_reference():
    """HAMMER_ROS_NO_NUMBA=1: ``plls`` is the reference bit for bit (in a fresh process)."""
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
            "import numpy as np\n"
            "from test_compiled_plls import random_case\n"
            "from hammer_ros.identification.piecewise_linear_ls import plls\n"
            "u, y, order, delay = random_case(7)\n"
            "a = plls(u, y, order, delay, instrumental=True, uncertainty=True)\n"
            "b = plls(u, y, order, delay, instrumental=True, uncertainty=True, compiled=False)\n"
            "print(np.array_equal(a.linear.b, b.linear.b), np.array_equal(a.uncertainty.poles_std,"
            " b.uncertainty.poles_std))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "HAMMER_ROS_NO_NUMBA": "1"}, check=True)
    assert out.stdout.split() == ["True", "True"], out.stderr
