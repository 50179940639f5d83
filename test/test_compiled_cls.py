"""The compiled CLS solve (``cls_kernel.cls_solve``) against the numpy reference on random systems:
estimates and confidence bounds equal to 1e-9 relative, for ARX and mu-Markov, orders 1-4, delays 0-3."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from relative_tolerance import assert_close

from hammer_ros.identification.correlation_least_squares import (
    cls_from_correlations,
    compiled_steps,
    correlation_functions,
    default_tau_max,
)
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.methods import IdentifyOptions, identify
from hammer_ros.identification.simulate import add_noise, simulate_hammerstein
from hammer_ros.identification.static_maps import PolynomialMap

pytest.importorskip("numba")

SAMPLES = 3000


def random_case(seed: int):
    """A random stable plant (order 1-4, relative degree 0-min(3, order), poles and zeros inside
    radius 0.9), a random cubic F with a positive slope, a Gaussian input with a random mean and 2 %
    output noise: (v, y, order, delay)."""
    rng = np.random.default_rng(seed)
    order = int(rng.integers(1, 5))
    delay = int(rng.integers(0, min(3, order) + 1))

    def roots(count: int) -> list[complex]:
        out: list[complex] = []
        while len(out) < count:
            if count - len(out) >= 2 and rng.random() < 0.5:
                z = 0.85 * np.sqrt(rng.random()) * np.exp(1j * rng.uniform(0.2, 2.9))
                out += [z, np.conj(z)]
            else:
                out.append(rng.uniform(-0.85, 0.85))
        return out

    linear = LinearModel.from_zeros_poles(roots(order - delay), roots(order))
    fmap = PolynomialMap([rng.normal(0, 0.1), 1.0, rng.normal(0, 0.5), rng.uniform(0.5, 4.0)])
    v = rng.normal(rng.normal(0, 0.05), 0.2, SAMPLES)
    y = add_noise(simulate_hammerstein(v, fmap, linear), 0.02, seed=rng)
    return v, y, order, delay


FIGURES = {
    "poles": lambda r: r.linear.poles, "zeros": lambda r: r.linear.zeros, "b": lambda r: r.linear.b,
    "a": lambda r: r.linear.a, "markov": lambda r: r.markov, "map": lambda r: r.nonlinearity.coefficients,
    "gain": lambda r: r.gain, "poles_std": lambda r: r.uncertainty.poles_std,
    "zeros_std": lambda r: r.uncertainty.zeros_std, "gain_std": lambda r: r.uncertainty.gain_std,
    "map_covariance": lambda r: r.uncertainty.map_covariance,
}


@pytest.mark.parametrize("structure", ["arx", "markov"])
@pytest.mark.parametrize("seed", range(12))
def test_the_compiled_solve_equals_the_reference(structure, seed):
    v, y, order, delay = random_case(1000 * seed + (structure == "markov"))
    options = IdentifyOptions(order=order, delay=delay, mu=30 if structure == "markov" else None)
    phi_vv, phi_yv = correlation_functions(v, y, default_tau_max(order, 1 if structure == "arx" else 30))
    assert compiled_steps(phi_vv, phi_yv, v, y, order, delay, 1 if structure == "arx" else 30, 3) is not None
    compiled = cls_from_correlations(phi_vv, phi_yv, v, y, options, structure)
    reference = cls_from_correlations(phi_vv, phi_yv, v, y, options, structure, compiled=False)
    assert reference.uncertainty is not None and compiled.uncertainty.how == reference.uncertainty.how
    for name, figure in FIGURES.items():
        assert_close(figure(compiled), figure(reference), f"{structure} order {order} delay {delay}: {name}")


def test_the_compiled_solve_with_other_settings_equals_the_reference():
    """mu 10 and tau_max 40 for mu-Markov, F of degree 1 and 5, a tau_max of 30 for ARX."""
    v, y, _, _ = random_case(7)
    cases = [("markov", IdentifyOptions(order=3, delay=1, mu=10, tau_max=40)),
             ("markov", IdentifyOptions(order=2, delay=1, mu=30, poly=5)),
             ("arx", IdentifyOptions(order=3, delay=1, tau_max=30, poly=1))]
    for structure, options in cases:
        tau_max = options.tau_max or default_tau_max(options.order, options.mu or 1)
        phi_vv, phi_yv = correlation_functions(v, y, tau_max)
        compiled = cls_from_correlations(phi_vv, phi_yv, v, y, options, structure)
        reference = cls_from_correlations(phi_vv, phi_yv, v, y, options, structure, compiled=False)
        for name, figure in FIGURES.items():
            assert_close(figure(compiled), figure(reference), f"{structure} {options}: {name}")


def test_batch_identify_keeps_the_reference_estimate_and_takes_the_compiled_bounds():
    """``identify`` (what ``reproduce`` prints) gives the reference's estimate bit for bit and the
    compiled bounds; the engine's path (``compiled`` None) gives the compiled estimate."""
    v, y, order, delay = random_case(3)
    options = IdentifyOptions(order=order, delay=delay)
    batch = identify("cls-markov", v, y, options)
    phi_vv, phi_yv = correlation_functions(v, y, default_tau_max(order, 30))
    reference = cls_from_correlations(phi_vv, phi_yv, v, y, options, "markov", compiled=False)
    compiled = cls_from_correlations(phi_vv, phi_yv, v, y, options, "markov")
    np.testing.assert_array_equal(batch.linear.b, reference.linear.b)
    np.testing.assert_array_equal(batch.nonlinearity.coefficients, reference.nonlinearity.coefficients)
    np.testing.assert_array_equal(batch.uncertainty.poles_std, compiled.uncertainty.poles_std)


def test_where_the_reference_decides_the_compiled_solve_steps_aside():
    """A record with a NaN, an ERA order above the Hankel size, an F without a linear term: the
    compiled solve hands over (None) and the reference raises or answers as before."""
    v, y, order, delay = random_case(11)
    phi_vv, phi_yv = correlation_functions(v, y, default_tau_max(order, 30))
    with_nan = y.copy()
    with_nan[10] = np.nan
    assert compiled_steps(phi_vv, phi_yv, v, with_nan, order, delay, 30, 3) is None
    assert compiled_steps(phi_vv, phi_yv, v, y, 4, 0, 2, 3) is None  # mu 2: a 1 x 1 Hankel matrix for order 4
    assert compiled_steps(phi_vv, phi_yv, v, y, order, delay, 30, 0) is None
    assert compiled_steps(phi_vv, phi_yv, v, y, order, delay, 30, 3) is not None


def test_the_kernel_records_the_digest_of_its_callees():
    """numba's cache checks only ``cls_kernel.py``'s source: a change to the callees' modules must change
    its ``CALLEE_DIGEST`` (until then ``cls_solve`` compiles without the cache)."""
    from hammer_ros.identification import cls_kernel

    assert cls_kernel.callee_digest() == cls_kernel.CALLEE_DIGEST, (
        f"write CALLEE_DIGEST = {cls_kernel.callee_digest()!r} in hammer_ros/identification/cls_kernel.py")


def test_a_second_process_loads_the_solve_from_the_cache(compiled_solve):
    """After this session compiled it (``compiled_solve``), another process takes ``cls_solve`` from numba's
    cache instead of compiling it."""
    script = ("import numpy as np\n"
              "from hammer_ros.identification.correlation_least_squares import compiled_steps, correlation_functions\n"
              "from hammer_ros.identification.cls_kernel import cls_solve\n"
              "v = np.random.default_rng(0).standard_normal(600)\n"
              "y = np.convolve(v, [0.0, 1.0, 0.5])[: v.size]\n"
              "compiled_steps(*correlation_functions(v, y, 66), v, y, 3, 1, 30, 3)\n"
              "print(sum(cls_solve.stats.cache_hits.values()), sum(cls_solve.stats.cache_misses.values()))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=True)
    assert done.stdout.split() == ["1", "0"], done.stdout + done.stderr
