"""Several runs (issue 50, item 1): separate experiments laid end to end, each from rest at its own
operating point, identified by every method without a regressor, correlation product or simulation
across a boundary; the same model from several files as from one file with a ``run`` column."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from hammer_ros.cli import main
from hammer_ros.identification.linear import LinearModel
from hammer_ros.identification.methods import METHODS, IdentifyOptions, identify
from hammer_ros.identification.runs import Runs
from hammer_ros.identification.simulation_error import preroll_simulate

PLANT = LinearModel(np.array([0.0, 1.0, 0.5]), np.array([1.0, -1.5, 0.7]))  # poles 0.75 +- 0.37j
TRUE_POLES = np.sort_complex(PLANT.poles)
RUNS, LENGTH = 8, 1500


def cubic(x: np.ndarray) -> np.ndarray:
    return x + 0.3 * x**2 + 0.2 * x**3


def linear_map(x: np.ndarray) -> np.ndarray:
    return 2.0 * x


def saturation(x: np.ndarray) -> np.ndarray:
    return 2.0 * np.clip(x, -0.5, 0.7)


def plant_output(fmap, v: np.ndarray, rest_at: float) -> np.ndarray:
    """y = PLANT F(v) from rest at the input ``rest_at`` (the plant reset there before the run)."""
    return preroll_simulate(lambda x: PLANT.simulate(fmap(x)), np.concatenate([[rest_at], v]), 500)[1:]


def runs_record(fmap, excitation, seed: int, noise: float = 0.02):
    """8 runs of 1500 samples; run i starts from rest at the operating point +-4 (1 + 0.1 i)
    (alternating), so the concatenation jumps at every boundary."""
    rng = np.random.default_rng(seed)
    vs, ys = [], []
    for i in range(RUNS):
        v = excitation(rng, LENGTH)
        vs.append(v)
        ys.append(plant_output(fmap, v, (-4.0, 4.0)[i % 2] * (1 + 0.1 * i)) + noise * rng.standard_normal(LENGTH))
    return np.concatenate(vs), np.concatenate(ys), Runs.from_lengths([LENGTH] * RUNS)


def pole_error(result) -> float:
    poles = np.sort_complex(result.poles)
    return float(np.max(np.abs(poles - TRUE_POLES))) if poles.size == TRUE_POLES.size else np.inf


# method -> (map, input, largest pole error with runs); each method on a signal it supports
CASES = {
    "cls-arx": (cubic, lambda rng, n: rng.standard_normal(n), 0.02),
    "cls-markov": (cubic, lambda rng, n: rng.standard_normal(n), 0.02),
    "ls-arx": (linear_map, lambda rng, n: rng.standard_normal(n), 1e-3),
    "plls-hammerstein": (saturation, lambda rng, n: rng.uniform(-1.0, 1.0, n), 1e-3),
    "bf-hammerstein": (cubic, lambda rng, n: 1.0 + rng.standard_normal(n), 0.01),
}
REGRESSION_METHODS = ("ls-arx", "plls-hammerstein")


@pytest.mark.parametrize("method", list(CASES))
def test_runs_from_different_operating_points(method):
    fmap, excitation, tolerance = CASES[method]
    v, y, runs = runs_record(fmap, excitation, seed=3)
    options = IdentifyOptions(order=2, delay=1)
    with_runs = pole_error(identify(method, v, y, replace(options, runs=runs)))
    concatenated = pole_error(identify(method, v, y, options))
    assert with_runs < tolerance, (method, with_runs)
    if method in REGRESSION_METHODS:  # the rows across a jump bias the concatenation
        assert concatenated > 5 * with_runs and concatenated > tolerance, (method, with_runs, concatenated)


def test_every_method_accepts_runs_and_bounds_stay_within_them():
    """Every method runs on a record of runs; the bounds are made (CLS: blocks of run centres,
    regressions: their rows, subseries: segments cut at the boundaries)."""
    v, y, runs = runs_record(cubic, lambda rng, n: 1.0 + rng.standard_normal(n), seed=5)
    u2 = np.sin(np.pi / 16 * np.arange(2048))
    harmonic = (u2, PLANT.simulate(cubic(u2)))
    for method in METHODS:
        options = IdentifyOptions(order=2, delay=1, runs=runs, harmonic=harmonic)
        result = identify(method, v, y, options)
        assert np.all(np.isfinite(result.poles)), method
        if method.startswith(("cls", "ls", "nls", "plls-hammerstein", "bf")):
            assert result.uncertainty is not None, method
            assert np.all(np.isfinite(result.uncertainty.poles_std)), method


def test_runs_window():
    runs = Runs((0, 100, 250), 400)
    assert runs.window(50, 300) == Runs((0, 50, 200), 250)
    assert runs.window(100, 250) == Runs((0,), 150)
    rows = runs.rows(3)
    assert rows.size == 400 - 9 and not np.isin([100, 101, 102, 250, 251, 252], rows).any()


def write_csv(path, v, y, labels=None) -> None:
    header, columns = "u,y", [v, y]
    if labels is not None:
        header, columns = header + ",run", [v, y, labels]
    np.savetxt(path, np.column_stack(columns), delimiter=",", header=header, comments="", fmt="%.17g")


def identify_json(capsys, *argv: str) -> dict:
    assert main(["identify", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("method", ["cls-markov", "plls-hammerstein"])
def test_run_files_identify_as_one_file_with_a_run_column(tmp_path, capsys, method):
    fmap, excitation, _ = CASES[method]
    v, y, runs = runs_record(fmap, excitation, seed=7)
    files = []
    for i, (part_v, part_y) in enumerate(zip(runs.split(v), runs.split(y))):
        files.append(tmp_path / f"r{i}.csv")
        write_csv(files[-1], part_v, part_y)
    write_csv(tmp_path / "all.csv", v, y, np.repeat(np.arange(RUNS) % 2, LENGTH))  # labels 0 1 0 1...: 8 runs
    options = ("--method", method, "--order", "2", "--delay", "1")
    separate = identify_json(capsys, *map(str, files), *options)
    together = identify_json(capsys, str(tmp_path / "all.csv"), *options)
    assert separate["runs"] == together["runs"] == RUNS
    np.testing.assert_allclose(separate["poles"], together["poles"], atol=1e-12)
    assert separate["fit_percent"] == pytest.approx(together["fit_percent"], abs=1e-9)
    assert np.max(np.abs(np.array(together["poles"]) @ [1, 1j] - TRUE_POLES)) < 0.02


def test_one_run_label_is_no_run_column(tmp_path, capsys):
    v, y, _ = runs_record(cubic, lambda rng, n: rng.standard_normal(n), seed=9)
    write_csv(tmp_path / "plain.csv", v, y)
    write_csv(tmp_path / "one.csv", v, y, np.full(v.size, 4.0))
    for method in ("cls-arx", "plls-hammerstein"):
        plain = identify_json(capsys, str(tmp_path / "plain.csv"), "--method", method, "--order", "2")
        one = identify_json(capsys, str(tmp_path / "one.csv"), "--method", method, "--order", "2")
        assert one == plain and one["runs"] == 1


def test_fit_is_per_run_from_rest():
    """Runs from rest at their first input sample, at operating levels far apart: with runs each run is
    simulated from rest at its own first input and the model explains them; concatenated, the
    simulation carries one run's level into the next and is charged for the jump."""
    rng = np.random.default_rng(11)
    vs, ys = [], []
    for i in range(RUNS):
        v = (-3.0, 3.0)[i % 2] + 0.5 * rng.standard_normal(600)
        vs.append(v)
        ys.append(plant_output(linear_map, v, v[0]) + 0.01 * rng.standard_normal(600))
    v, y, runs = np.concatenate(vs), np.concatenate(ys), Runs.from_lengths([600] * RUNS)
    result = identify("ls-arx", v, y, IdentifyOptions(order=2, delay=1, runs=runs))
    per_run = result.to_json(v, y, runs)["fit_percent"]
    across = result.to_json(v, y)["fit_percent"]
    assert per_run > 99.5, per_run
    assert across < 95.0, across
