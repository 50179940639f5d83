"""identify --refine: every method's estimate refined on the simulation error."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.identification.linear import LinearModel, root_rss_error
from hammer_ros.identification.methods import IdentifyOptions, identify
from hammer_ros.identification.refinement import piecewise_linear_from, refine_result
from hammer_ros.identification.static_maps import PolynomialMap

MAPS = (lambda x: x + 0.3 * x**3, lambda x: np.tanh(1.5 * x), lambda x: np.clip(x, -0.8, 1.0),
        lambda x: np.sign(x) * np.maximum(np.abs(x) - 0.3, 0.0), lambda x: np.where(x > 0, x, 0.3 * x))


def random_plant(rng: np.random.Generator) -> LinearModel:
    """Order 2-3: a complex pair half the time, real poles 0.1 apart, a zero half the time
    (kept 0.3 away from every pole: a near-cancelling pair has no well-defined pole)."""
    order = int(rng.integers(2, 4))
    poles: list[complex] = []
    if rng.random() < 0.5:
        radius, angle = rng.uniform(0.5, 0.9), rng.uniform(0.2, 1.2)
        poles += [radius * np.exp(1j * angle), radius * np.exp(-1j * angle)]
    while len(poles) < order:
        p = rng.uniform(0.1, 0.9)
        if all(abs(p - q) > 0.1 for q in poles):
            poles.append(p)
    z = rng.uniform(-0.7, 0.7)
    zeros = [z] if rng.random() < 0.5 and all(abs(z - q) > 0.3 for q in poles) else []
    return LinearModel.from_zeros_poles(zeros, poles, rng.uniform(0.5, 2.0) * rng.choice([-1.0, 1.0]))


@pytest.mark.parametrize("method", ["plls-hammerstein", "cls-markov"])
def test_refinement_on_twenty_random_hammerstein_systems(method):
    """30 dB output noise, Gaussian input, five kinds of map: the refined poles are close to the
    truth wherever the method starts (the issue's goal: median pole RSS <= 0.01, p90 <= 0.05)."""
    raw, refined = [], []
    for seed in range(20):
        rng = np.random.default_rng(7000 + seed)
        plant = random_plant(rng)
        v = rng.standard_normal(4000)
        x = plant.simulate(MAPS[seed % len(MAPS)](v))
        y = x + np.std(x) * 10 ** (-30 / 20) * rng.standard_normal(v.size)
        partition = tuple(np.quantile(v, np.linspace(0.05, 0.95, 9))) if method.startswith("plls") else None
        estimate = identify(method, v, y, IdentifyOptions(order=plant.order, delay=1, partition=partition))
        result = refine_result(estimate, v, y)
        assert result.extra["refined"]["cost"] <= result.extra["refined"]["cost_start"]
        raw.append(root_rss_error(plant.poles, estimate.poles))
        refined.append(root_rss_error(plant.poles, result.poles))
    assert np.median(refined) <= 0.01 and np.quantile(refined, 0.9) <= 0.05, (np.median(refined), refined)
    # the refinement is what gets there; PLLS's instrumental-variable start is already consistent under
    # output noise (median raw RSS 0.0028 against 0.0019 refined), the refinement must still improve it
    assert np.median(refined) < (0.8 if method.startswith("plls") else 0.5) * np.median(raw)


def test_a_polynomial_map_is_refined_as_piecewise_linear_through_its_values():
    f = PolynomialMap(np.array([0.1, 1.0, 0.0, 0.3]))
    v = np.random.default_rng(0).standard_normal(2000)
    m = piecewise_linear_from(f, v)
    assert np.allclose(m(m.breakpoints), f(m.breakpoints))
    inside = np.linspace(m.breakpoints[0], m.breakpoints[-1], 200)
    assert np.max(np.abs(m(inside) - f(inside))) < 0.05 * np.ptp(f(inside))


@pytest.mark.parametrize("method", ["cls-arx", "ls-arx", "plls-feedback", "bf-feedforward", "nls-markov"])
def test_identify_refine_from_the_cli(tmp_path, capsys, method):
    rng = np.random.default_rng(3)
    plant = LinearModel.from_zeros_poles([], [0.7, 0.4], 1.0)
    v = rng.standard_normal(3000)
    y = plant.simulate(np.tanh(v)) + 0.01 * rng.standard_normal(v.size)
    path = tmp_path / "record.csv"
    np.savetxt(path, np.column_stack([v, y]), delimiter=",", header="u,y", comments="")
    extra = ["--partition", "-0.5,0,0.5"] if method.startswith("plls") else []
    assert main(["identify", str(path), "--method", method, "--order", "2", *extra, "--json"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert main(["identify", str(path), "--method", method, "--order", "2", *extra, "--refine", "--json"]) == 0
    refined = json.loads(capsys.readouterr().out)
    assert refined["method"] == method and "refined" in refined and "refined" not in plain
    assert refined["rms"] <= plain["rms"] * 1.02  # V leaves out the first settling samples
    assert refined["refined"]["cost"] <= refined["refined"]["cost_start"]
