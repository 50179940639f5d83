"""Semiparametric identification (paper 002): maps, delay, symmetry search, inverse, CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hammer_ros.errors import IdentificationError
from hammer_ros.identification.excitation import gaussian_white_noise, sine
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.methods import IdentifyOptions, identify
from hammer_ros.identification.semiparametric import (
    harmonic_period,
    map_error,
    minimum_phase_counterpart,
    nonharmonic_phase_shift,
    semiparametric,
    symmetry_error,
)
from hammer_ros.identification.simulate import simulate_hammerstein
from hammer_ros.reproduce.semiparametric import EXAMPLES, rows

HAMMER = [str(Path(sys.executable).parent / "hammer-ros")]


@pytest.mark.parametrize("name", ["5.1", "5.2", "6.1"])
def test_map_within_5_percent_with_1_percent_noise(name):
    example = EXAMPLES[name]
    estimate = example.identify(noise=0.01, seed=3)
    assert example.map_error(estimate.nonlinearity) < 0.05
    assert estimate.shift.even == (name == "5.2")


@pytest.mark.parametrize(("name", "delay"), [("5.1", 0), ("5.1", 1), ("5.1", 2), ("5.2", 1), ("6.1", 0), ("6.1", 1)])
def test_delay_d_minus_l_found_exactly_without_noise(name, delay):
    example = EXAMPLES[name]
    estimate = example.identify(delay=delay)
    assert estimate.shift.delay == example.relative_degree - delay
    assert example.map_error(estimate.nonlinearity) < 0.01


def test_even_nonlinearity_runner_up_gives_the_wrong_map():
    """Paper 002 Fig. 8b: for the even H the shift phi + pi/2 is as symmetric but wrong."""
    example = EXAMPLES["5.2"]
    estimate = example.identify()
    assert estimate.shift.even
    assert abs(estimate.shift.alternative - estimate.shift.delay) == example.period / 4
    assert example.map_error(estimate.alternative_nonlinearity()) > 0.3
    assert example.map_error(estimate.nonlinearity) < 0.01


def test_even_nonlinearity_with_zero_mean_rich_input_is_refused():
    example = EXAMPLES["5.2"]
    u = gaussian_white_noise(5000, 3.5, seed=1)
    y = simulate_hammerstein(u, example.nonlinearity, example.linear)
    _, _, u2, y2 = example.records()
    with pytest.raises(IdentificationError, match="non-zero mean"):
        semiparametric(u, y, u2, y2, example.order, 2)


def test_non_minimum_phase_model_uses_a_stable_inverse():
    plant = LinearModel.from_zeros_poles([1.6, -0.4], [0.8, 0.5 + 0.3j, 0.5 - 0.3j], dc_gain=1.0)
    inverse = minimum_phase_counterpart(plant, 1)
    assert np.all(np.abs(inverse.zeros) <= 1.0)
    w = np.linspace(0.0, np.pi, 50)
    assert np.allclose(np.abs(_response(inverse, w)), np.abs(_response(plant, w)))

    def cubic(u):
        return 0.6 * (u + 1) ** 3 - 1

    u = gaussian_white_noise(4000, 0.3, seed=2)
    u2 = sine(6 * 200, 2 * np.pi / 200, 1.0)
    y, y2 = (simulate_hammerstein(x, cubic, plant) for x in (u, u2))
    estimate = semiparametric(u, y, u2, y2, 3, 1)
    assert np.all(np.isfinite(estimate.reconstruction.v))
    assert map_error(estimate.nonlinearity, cubic, -1, 1) < 0.02


def _response(model, w):
    return np.polyval(model.b[::-1], np.exp(-1j * w)) / np.polyval(model.a[::-1], np.exp(-1j * w))


def test_symmetry_error_finds_the_sine_peak_and_quarter_points():
    n0 = 40
    u = np.sin(2 * np.pi * np.arange(n0) / n0)
    beta = symmetry_error(u)
    assert int(np.argmin(beta)) == n0 // 2  # doubled index of the peak at n0/4
    assert beta[n0 // 2] == pytest.approx(0.0, abs=1e-12)
    assert beta[0] == pytest.approx(1.0)  # about the zero crossing u is antisymmetric
    shifted = np.roll(np.abs(u) ** 3 + u, 3)
    shift = nonharmonic_phase_shift(u, shifted)
    assert shift.delay == 3 and not shift.even


def test_harmonic_period_and_its_errors():
    assert harmonic_period(sine(6000, np.pi / 1000, 5.0, phase=0.4)) == 2000
    with pytest.raises(IdentificationError, match="not a single sine"):
        harmonic_period(gaussian_white_noise(3000, 1.0, seed=0))
    with pytest.raises(IdentificationError, match="whole number"):
        harmonic_period(sine(3000, 2 * np.pi / 37.5))


def test_identify_method_reports_delay_and_map():
    example = EXAMPLES["5.1"]
    u, y, u2, y2 = example.records(seed=5)
    result = identify("semiparametric", u, y, IdentifyOptions(order=7, delay=0, harmonic=(u2, y2)))
    doc = result.to_json(u2, y2)  # fit of G_hat H_hat where H_hat is known: the harmonic's range
    assert doc["delay_found"] == 2 and doc["relative_degree"] == 2
    assert doc["nonlinearity"]["kind"] == "nonparametric"
    assert doc["fit_percent"] > 95.0
    with pytest.raises(IdentificationError, match="--harmonic"):
        identify("semiparametric", u, y, IdentifyOptions(order=7, delay=0))


def _write_csv(path, u, y):
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")


def test_cli_identify_semiparametric(tmp_path):
    example = EXAMPLES["6.1"]
    u, y, u2, y2 = example.records(noise=0.01, seed=7)
    _write_csv(tmp_path / "rich.csv", u, y)
    _write_csv(tmp_path / "sine.csv", u2, y2)
    base = [*HAMMER, "identify", str(tmp_path / "rich.csv"), "--method", "semiparametric", "--order", "2"]
    done = subprocess.run([*base, "--harmonic", str(tmp_path / "sine.csv"), "--json"],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    points = np.array(doc["nonlinearity"]["points"])
    assert doc["method"] == "semiparametric" and doc["nonlinearity"]["kind"] == "nonparametric"
    assert points.shape[1] == 2 and points[:, 0].min() < -4.9 and points[:, 0].max() > 4.9
    assert map_error(lambda x: np.interp(x, *points.T), example.nonlinearity, -5, 5) < 0.05
    assert isinstance(doc["delay_found"], int)

    missing = subprocess.run(base, capture_output=True, text=True, check=False)
    assert missing.returncode == 2
    assert "--harmonic" in missing.stderr and "Traceback" not in missing.stderr


def test_reproduce_rows():
    table = rows(1, 0)
    assert {"paper", "table", "case", "quantity", "published", "ours"} <= set(table[0])
    delays = [r for r in table if r["quantity"].startswith("delay d - l found")]
    assert [r["ours"] for r in delays] == [1, 1, 0]
